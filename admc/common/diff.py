"""Which settings differ: the one comparison behind every "changed since" message."""

from __future__ import annotations

from typing import Any


def differing_keys(have: Any, want: Any, prefix: str = "") -> list[str]:
    """Dotted keys at which two JSON values differ."""
    if isinstance(have, dict) and isinstance(want, dict):
        out = []
        for key in sorted(set(have) | set(want), key=str):
            name = f"{prefix}.{key}" if prefix else str(key)
            if key not in have or key not in want:
                out.append(name)
            else:
                out.extend(differing_keys(have[key], want[key], name))
        return out
    return [] if have == want else [prefix or "<value>"]
