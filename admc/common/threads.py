"""torch's OpenMP pool, kept out of the way of other engines' threads."""
from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch


@contextlib.contextmanager
def torch_inline() -> Iterator[None]:
    """Inside the block, torch's CPU ops run inline on the calling thread, not in its OpenMP pool.

    The pool's threads spin for milliseconds after each op (libgomp's default wait policy: the spin
    count, not a time), so on a 2-core CPU whatever runs next in OpenVINO's, OIDN's or FLIP's own
    threads starts without its cores. Around the glue of an exported graph (copies too small to gain
    from two threads) and around Table 1's scoring between timed calls: on the demo's 160x160 test
    images admc took 33-37 ms with the pool spinning and 20-21 ms without (docs/engines.md)."""
    threads = torch.get_num_threads()
    if threads == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
