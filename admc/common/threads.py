"""torch's OpenMP pool, kept out of the way of other engines' threads."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def torch_inline() -> Iterator[None]:
    """Inside the block, torch's CPU ops run inline on the calling thread, not in its OpenMP pool.

    The pool's threads spin after each op before they sleep (libgomp: GOMP_SPINCOUNT, see
    admc/__init__.py), so on a 2-core CPU what runs next in OpenVINO's or OIDN's own threads starts
    without its cores. The denoiser's glue around an exported graph (tiling, flips, casts) is copies too
    small to gain from two threads: inline, the demo's 160x160 test images took admc 16-18 ms each
    instead of 22-24 ms (docs/engines.md)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
