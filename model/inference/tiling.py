"""Tiled network calls: an image of any size through a generator in bounded memory, seamlessly.

Each tile's network input is its core region plus a halo as wide as the network's receptive field
radius (see `receptive_radius`); only the core of the output is kept. Every kept pixel then sees exactly
the inputs it sees in an untiled run, so a tiled image equals the untiled one up to float rounding: no
seams, and no blending window is needed. No padding is added: crops are taken inside the image (shifted
inwards at its borders), so at the image border the network's own (replicate) padding applies just as
in an untiled run and as at the borders of the 128x128 training patches. Any size works, 1x1 included.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch
from torch import Tensor, nn

from ..nets.generator import Generator


CPU_TILE = 320
"""A CPU's default tile core edge: small enough that a tile's activations stay in the last-level cache. On
the 2-core EPYC (32 MB L3) the small model's network time for 1280x720 was 2.4-2.5 s in tiles of 320-384
against 2.9 s in tiles of 512 (docs/benchmarks.md)."""
GPU_TILE = 512
"""A GPU's: it has no cache cliff at these sizes, and a larger tile repeats fewer halo pixels."""
OPENVINO_TILE = 640
"""OpenVINO's on a CPU: its kernels block for the cache themselves, so fewer, larger tiles repeat fewer halo
pixels and calls. 1280x720, small model, bf16, 2-core EPYC with AVX512-BF16, three alternating runs of 7:
the network took 512-658 ms in tiles of 640 against 615-759 ms in tiles of 320 (docs/engines.md)."""
HALOS_PER_TILE = 8
"""A tile is at least this many halos wide, so the halo adds at most (1 + 2/8)^2 = 1.56x the pixels: the
multi-scale body's 116-px halo gets 928-px tiles (1280x720 in 8.1 s on the EPYC, 11.1 s in tiles of 512)."""


def default_tile(device: torch.device, halo: int, engine: str = "torch") -> int:
    """The tile core edge a denoiser on `device` with this `halo` and `engine` uses unless told otherwise."""
    edge = GPU_TILE if device.type == "cuda" else OPENVINO_TILE if engine == "openvino" else CPU_TILE
    return max(edge, HALOS_PER_TILE * halo)


def receptive_radius(generator: Generator) -> int:
    """How many pixels away an input can still change an output pixel of `generator` (see its
    `receptive_radius` method: 36 for the paper's residual body, a 73x73 receptive field)."""
    if not isinstance(generator, Generator):
        raise TypeError(
            f"receptive_radius needs an admc Generator, got {type(generator).__name__}; "
            f"pass overlap= explicitly for other modules"
        )
    return generator.receptive_radius()


def axis_windows(size: int, tile: int, halo: int, align: int = 1) -> list[tuple[int, int, int, int]]:
    """(core_start, core_end, crop_start, crop_end) along one axis.

    Cores split [0, size) into ceil(size / tile) near-equal parts (balanced, so no sliver tile).
    Every crop has the same length, min(size, longest core + 2 * halo), so tiles can be batched, and
    is shifted inwards at the image borders; each core then has `halo` pixels of real image on every
    side that is not the image border. With `align` > 1 (a multi-scale generator) each crop's start
    is then moved down to a multiple of `align`, so the network sees the untiled image's pixel grid;
    crops grow by less than `align`.
    """
    if size < 1 or tile < 1 or halo < 0 or align < 1:
        raise ValueError(
            f"axis_windows: need size >= 1, tile >= 1, halo >= 0, align >= 1; got {size}, {tile}, {halo}, {align}"
        )
    count = math.ceil(size / tile)
    bounds = [round(i * size / count) for i in range(count + 1)]
    crop = min(size, max(b - a for a, b in zip(bounds, bounds[1:])) + 2 * halo)
    windows = []
    for start, end in zip(bounds, bounds[1:]):
        crop_start = min(max(start - halo, 0), size - crop)
        windows.append((start, end, crop_start - crop_start % align, crop_start + crop))
    return windows


Window = tuple[tuple[int, int, int, int], tuple[int, int, int, int]]
"""A tile: its (core_start, core_end, crop_start, crop_end) along the rows, then the columns."""


def tile_calls(
    noisy: Tensor, feats: Tensor, tile: int, halo: int, align: int = 1, base: Tensor | None = None
) -> tuple[list[Window], list[tuple[Tensor, ...]]]:
    """The tiles of (1, C, H, W) inputs and each tile's generator inputs (views of its crop)."""
    _, _, height, width = noisy.shape
    windows = [
        (rows, columns)
        for rows in axis_windows(height, tile, halo, align)
        for columns in axis_windows(width, tile, halo, align)
    ]
    crops = [(..., slice(cy0, cy1), slice(cx0, cx1)) for (_, _, cy0, cy1), (_, _, cx0, cx1) in windows]
    return windows, [(noisy[crop], feats[crop], *(() if base is None else (base[crop],))) for crop in crops]


def paste(windows: list[Window], outputs: Iterable[Tensor], like: Tensor) -> Tensor:
    """The tiles' outputs (in `windows`' order) as one float32 (1, 3, H, W) image of `like`'s size: each
    tile's core."""
    _, _, height, width = like.shape
    out = torch.empty((1, 3, height, width), dtype=torch.float32, device=like.device)
    for ((y0, y1, cy0, _), (x0, x1, cx0, _)), output in zip(windows, outputs, strict=True):
        out[..., y0:y1, x0:x1] = output[..., y0 - cy0 : y1 - cy0, x0 - cx0 : x1 - cx0].float()
    return out


def run_tiled(
    generator: nn.Module, noisy: Tensor, feats: Tensor, tile: int, halo: int, align: int = 1, base: Tensor | None = None
) -> Tensor:
    """`generator(noisy, feats[, base])` on (1, C, H, W) tensors, tile by tile; the output is float32.

    With halo >= receptive_radius(generator) and align = generator.alignment the result equals the
    untiled call up to float rounding. The tiles run in turn; the denoiser hands an exported graph's tiles
    to engines.run_together instead, to run several at once.
    """
    windows, calls = tile_calls(noisy, feats, tile, halo, align, base)
    return paste(windows, (generator(*call) for call in calls), noisy)
