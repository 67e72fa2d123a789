"""Exposure normalisation at inference: a dim image is scaled up to the brightness the networks trained on.

The networks see log1p(radiance). Above ~1 an exposure change only shifts the log values, but a dim
image sits in log1p's near-linear range, where its noise is too small in absolute terms for the
networks to tell from detail. Measured on the 32 val scenes of the pretraining corpus with the shipped
weights (experiments/exposure_check.py), admc's relMSE as a multiple of its input's, at 4 / 64 spp: 0.12 / 0.35
at their own exposure, 0.29 / 2.08 at 1/16 of it (worse than the input); normalised, 0.12 / 0.33 and
0.13 / 0.36, and worse than without (by more than 0.1%) on 1 of the 32 at their own exposure at 4 spp.
Multiplying the radiance by a gain k >= 1 (a power of two) before the networks and dividing their
output by k is an exact exposure change of the render, so the denoised image stays in the input's
units. Bright images keep k = 1: scaling them down measured worse, not better.

The same holds inside one image: the dark regions of a bright image (shadows, the dim side of an
object) sit in log1p's linear range too, where the networks' small absolute error in the log domain is
a large relative one. So a second pass denoises the dark region again at DARK_GAIN times the exposure
(dark_region), and dark_weights() takes each pixel from it by how dark the first pass found
it. Measured with the shipped weights, ensemble 4, as multiples of one pass, at 4 / 16 / 64 spp
(docs/design-decisions.md, "Dark pass").
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from ..transforms import RADIANCE_MAX

TRAINED_BRIGHTNESS = 0.21
"""Median brightness() of the pretraining corpus's noisy renders (configs/pretrain.toml, its 114 train
scenes: 0.212 at 4 spp, 0.215 at 64 spp; its 10th percentile is 0.053)."""

LUMINANCE = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
LIT = 1e-6
"""Pixels darker than this (a black background, samples that found no light) carry no exposure."""


def brightness(radiance: np.ndarray) -> float:
    """Geometric mean luminance of the lit pixels of an (H, W, 3) linear image; 0 when none is lit.

    The geometric mean follows the log values the networks see, and ignoring unlit pixels keeps a
    small object on a black background as bright as the object.
    """
    luminance = np.asarray(radiance, dtype=np.float32) @ LUMINANCE
    lit = luminance[np.isfinite(luminance) & (luminance > LIT)]
    return float(np.exp(np.mean(np.log(lit)))) if lit.size else 0.0


def exposure_gain(radiance: np.ndarray) -> float:
    """A power of two k >= 1 that brings a dim image's brightness() to within a factor sqrt(2) of
    TRAINED_BRIGHTNESS, no further than keeps its brightest value within RADIANCE_MAX (a clipped emitter
    would come back darker); 1 for an image at least that bright. Powers of two scale float values
    exactly, so the same image at any exposure reaches the networks as the same values."""
    level = brightness(radiance)
    if level <= 0.0 or level >= TRAINED_BRIGHTNESS:
        return 1.0
    steps = round(np.log2(TRAINED_BRIGHTNESS / level))
    peak = float(np.max(radiance, initial=0.0, where=np.isfinite(radiance)))
    if peak > 0:
        steps = min(steps, int(np.floor(np.log2(RADIANCE_MAX / peak))))
    return float(2.0 ** max(steps, 0))


DARK_GAIN = 64.0
"""The second pass's exposure, as a multiple of the first's (a power of two: exact, like exposure_gain)."""
DARK_LEVEL = 0.3
"""Luminance, at the first pass's exposure, below which a pixel starts taking the second pass; it takes
it wholly at DARK_LEVEL / DARK_GAIN, where the second pass brings it to DARK_LEVEL."""
DARK_SMOOTHING = 1.5
"""Gaussian sigma (pixels) of the luminance that decides: neighbours decide together, so the blend
follows regions, not the residual noise of single pixels."""


def dark_weights(denoised: np.ndarray, gain: float, coverage: np.ndarray) -> np.ndarray:
    """(H, W, 1) share of the DARK_GAIN pass per pixel of an (H, W, 3) first-pass output (in the input's
    units, denoised at `gain`): 0 from DARK_LEVEL up, 1 at DARK_LEVEL / DARK_GAIN and below, linear in
    log2 luminance between. 0 on environment pixels (coverage 0), which both passes leave as they are.

    Computed on the luminance times `gain`, so an image at any exposure gets the same weights."""
    luminance = gaussian_filter(
        np.asarray(denoised, dtype=np.float32) @ LUMINANCE * np.float32(gain), DARK_SMOOTHING, mode="reflect"
    )
    stops = np.log2(DARK_LEVEL / np.maximum(luminance, np.float32(1e-30)))
    weights = np.clip(stops / np.log2(DARK_GAIN), 0.0, 1.0)
    return np.where(coverage[..., 0] > 0, weights, 0.0)[..., None].astype(np.float32)


def dark_region(weights: np.ndarray, halo: int, alignment: int) -> tuple[slice, slice]:
    """The rows and columns the dark pass must run on: the bounding box of the pixels with a weight, grown
    by the networks' halo and started on their grid (tiling.axis_windows' two conditions for exactness).
    A small object's shadows on a black background need a fraction of the image."""

    def span(lit: np.ndarray) -> slice:
        first, last = np.flatnonzero(lit)[[0, -1]]
        start = max(int(first) - halo, 0)
        return slice(start - start % alignment, min(int(last) + 1 + halo, lit.size))

    dark = weights[..., 0] > 0
    return span(dark.any(axis=1)), span(dark.any(axis=0))
