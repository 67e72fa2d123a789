"""Field checks of the settings dataclasses: each raises ValueError("<field>: <problem>"), which the
config loader reports with the field's section."""
from __future__ import annotations


def require(ok: bool, field: str, problem: str) -> None:
    if not ok:
        raise ValueError(f"{field}: {problem}")


def positive_ints(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        require(isinstance(value, int) and not isinstance(value, bool) and value >= 1, name,
                f"must be an int >= 1, got {value!r}")


def non_negative_ints(obj: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(obj, name)
        require(isinstance(value, int) and not isinstance(value, bool) and value >= 0, name,
                f"must be an int >= 0, got {value!r}")
