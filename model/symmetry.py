"""The 8 symmetries of the square on (N, C, H, W) tensors, for test-time self-ensembling.

The same codes and normal rule as training's augmentation (data.augment): the networks learned every
symmetry of a patch as equally likely, so each one gives an equally good, slightly different estimate,
and their average has less of the networks' own error. Codes apply transpose, flip rows, flip columns
in that order; `undo` applies their inverses in reverse.
"""
from __future__ import annotations

from torch import Tensor

from .data import FLIP_COLS, FLIP_ROWS, NORMAL_X, NORMAL_Y, TRANSPOSE

HALF_TURN = FLIP_ROWS | FLIP_COLS
ENSEMBLE_CODES = {1: (0,), 2: (0, TRANSPOSE), 4: (0, TRANSPOSE, HALF_TURN, HALF_TURN | TRANSPOSE),
                  8: tuple(range(8))}
"""Symmetries averaged for an ensemble of each size (the keys are layout.ENSEMBLES): the identity, then
its transpose, then the half turn of both."""


def apply(x: Tensor, code: int, normals: bool = False) -> Tensor:
    """Symmetry `code` of `x`; with `normals`, channels NORMAL_X and NORMAL_Y are encoded view-space
    normals (v = (n + 1) / 2) and change as the geometry does (see data.augment)."""
    if code & TRANSPOSE:
        x = x.transpose(-2, -1)
        if normals:
            x = x.clone()
            nx, ny = x[:, NORMAL_X].clone(), x[:, NORMAL_Y].clone()
            x[:, NORMAL_X], x[:, NORMAL_Y] = 1.0 - ny, 1.0 - nx
    if code & FLIP_ROWS:
        x = x.flip(-2)
        if normals:
            x[:, NORMAL_Y] = 1.0 - x[:, NORMAL_Y]
    if code & FLIP_COLS:
        x = x.flip(-1)
        if normals:
            x[:, NORMAL_X] = 1.0 - x[:, NORMAL_X]
    return x


def undo(x: Tensor, code: int) -> Tensor:
    """The inverse of `apply(., code)` for images without normal channels (the networks' outputs)."""
    if code & FLIP_COLS:
        x = x.flip(-1)
    if code & FLIP_ROWS:
        x = x.flip(-2)
    if code & TRANSPOSE:
        x = x.transpose(-2, -1)
    return x
