"""The 8 symmetries of the square (flips and transpose) on (..., C, H, W) tensors: training's
augmentation and inference's test-time self-ensemble.

One definition for both: the networks learned every symmetry of a patch as equally likely, so each one
gives an equally good, slightly different estimate, and their average has less of the networks' own
error. Codes 0..7 are 3 bits, applied in this order: transpose, flip rows, flip columns; `undo`
applies their inverses in reverse. The view-space normal channels change with the geometry, so a
flipped patch is a patch that could have been rendered.
"""

from __future__ import annotations

from torch import Tensor

from admc.common.layout import NORMAL

TRANSPOSE, FLIP_ROWS, FLIP_COLS = 1, 2, 4
N_SYMMETRIES = 8
NORMAL_X, NORMAL_Y = NORMAL.start, NORMAL.start + 1  # view-space normal (x right, y up), stored as (n + 1) / 2

HALF_TURN = FLIP_ROWS | FLIP_COLS
ENSEMBLE_CODES = {1: (0,), 2: (0, TRANSPOSE), 4: (0, TRANSPOSE, HALF_TURN, HALF_TURN | TRANSPOSE), 8: tuple(range(8))}
"""Symmetries averaged for an ensemble of each size (the keys are layout.ENSEMBLES): the identity, then
its transpose, then the half turn of both."""


def apply(x: Tensor, code: int, normals: bool = False) -> Tensor:
    """Symmetry `code` of `x`, which is left alone; with `normals`, channels NORMAL_X and NORMAL_Y are
    encoded view-space normals, which change sign (v -> 1 - v) as the image geometry does.

    Image rows run downward while view-space y runs up, so: flipping columns negates x, flipping
    rows negates y, and transposing (a mirror on the anti-diagonal in view space) maps
    (x, y) -> (-y, -x).
    """
    if not 0 <= code < N_SYMMETRIES:
        raise ValueError(f"symmetry code must be in 0..{N_SYMMETRIES - 1}, got {code}")
    if code & TRANSPOSE:
        x = x.transpose(-2, -1)
        if normals:
            x = x.clone()
            nx, ny = x[..., NORMAL_X, :, :].clone(), x[..., NORMAL_Y, :, :].clone()
            x[..., NORMAL_X, :, :], x[..., NORMAL_Y, :, :] = 1.0 - ny, 1.0 - nx
    if code & FLIP_ROWS:
        x = x.flip(-2)
        if normals:
            x[..., NORMAL_Y, :, :] = 1.0 - x[..., NORMAL_Y, :, :]
    if code & FLIP_COLS:
        x = x.flip(-1)
        if normals:
            x[..., NORMAL_X, :, :] = 1.0 - x[..., NORMAL_X, :, :]
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
