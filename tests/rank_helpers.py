"""Functions the distributed tests run inside launched ranks: a module of its own, so that each rank
imports only torch and admc.model, not the test module's render and pipeline imports."""

import torch

from admc.model.training import distributed


def outlive_a_peer() -> str:
    """Rank 1 leaves at once; rank 0's next collective must say so."""
    if distributed.current().rank == 1:
        return ""
    try:
        distributed.agree(True, torch.device("cpu"))
    except distributed.RankFailed as exc:
        return str(exc)
    return "no error"
