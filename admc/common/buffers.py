"""The render buffers, defined once: each layer's channels, its valid range, and the one sanitiser.

Rendering, EXR files, tiling, the transforms, inference and the OIDN calls all read their layer names
and rules from here, so a buffer cannot be valid on one path and repaired differently on another.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .layout import FP16_MAX

RADIANCE_MAX = FP16_MAX
"""Linear radiance is clamped here (+Inf and huge fireflies alike), so every stored value also
inverts to an FP16-representable linear value. Directly seen emitters above it are clipped."""

VARIANCE_MAX = RADIANCE_MAX**2
"""A variance buffer's bound: the variance of a radiance clamped at RADIANCE_MAX."""


@dataclass(frozen=True)
class Layer:
    """One buffer: its EXR channels and valid range [low, high] (high None: unbounded above).

    Sanitising sets NaN to `nan`, -Inf to `low`, +Inf to `high` and clips finite values into the
    range. Where there is no high, +Inf also becomes `nan`: a depth without a finite distance is no
    hit, and an infinite pixel of the beauty has no value a baseline denoiser could spread.
    """

    channels: tuple[str, ...]
    low: float
    high: float | None
    nan: float = 0.0


RGB = ("R", "G", "B")
_RADIANCE = Layer(RGB, 0.0, RADIANCE_MAX)

BEAUTY = ""
"""The final image as plain R, G, B channels (what viewers show first)."""

LAYERS: dict[str, Layer] = {
    BEAUTY: Layer(RGB, 0.0, None),  # diffuse + specular: each may reach RADIANCE_MAX
    "diffuse": _RADIANCE,
    "specular": _RADIANCE,
    "albedo": Layer(RGB, 0.0, 1.0),
    "normal": Layer(("X", "Y", "Z"), -1.0, 1.0),  # view space, unit length
    "depth": Layer(("Z",), 0.0, None),  # distance to the first non-delta hit; 0: none
    "coverage": Layer(("A",), 0.0, 1.0),  # share of the pixel's samples that hit a surface
    "diffuse_var": Layer(RGB, 0.0, VARIANCE_MAX),  # the variance of each pixel's mean, per branch
    "specular_var": Layer(RGB, 0.0, VARIANCE_MAX),
}

DENOISER_LAYERS = ("diffuse", "specular", "albedo", "normal", "depth", "coverage")
"""What a denoiser reads: the two radiance branches and the sources of the feature channels."""
VARIANCE_LAYERS = ("diffuse_var", "specular_var")
"""What a denoiser with model.noise_input reads besides: each branch's noise, as the renderer measured it."""
MISSING_DEPTH = 1.0
"""Depth given to images that have none: every pixel then gets the depth feature 1.0, the value of
environment pixels (no geometry information), and coverage 1."""
MISSING_LAYERS = {"depth": MISSING_DEPTH, "coverage": 1.0}
"""What fills a layer the input lacks, at every pixel."""


def sanitize(x: np.ndarray, name: str) -> tuple[np.ndarray, dict[str, int]]:
    """Replace NaN, +-Inf and out-of-range values of layer `name` by its rule; count each case.

    Returns a new float32 array and {"nan", "posinf", "neginf", "below_min", "above_max"} counts.
    """
    if name not in LAYERS:
        raise ValueError(f"sanitize: unknown buffer {name!r} (known: {', '.join(map(repr, LAYERS))})")
    layer = LAYERS[name]
    lo, hi = layer.low, layer.high
    x = np.asarray(x, dtype=np.float32)
    if _in_range(x, lo, hi):
        return x.copy(), dict.fromkeys(("nan", "posinf", "neginf", "below_min", "above_max"), 0)
    nan = np.isnan(x)
    posinf = np.isposinf(x)
    neginf = np.isneginf(x)
    finite = ~(nan | posinf | neginf)
    below = finite & (x < lo)
    above = finite & (x > hi) if hi is not None else np.zeros_like(finite)
    clean = np.where(finite, x, np.float32(layer.nan))
    clean[posinf] = hi if hi is not None else layer.nan
    clean[neginf] = lo
    clean = np.clip(clean, lo, hi) if hi is not None else np.maximum(clean, lo)
    counts = {
        "nan": int(nan.sum()),
        "posinf": int(posinf.sum()),
        "neginf": int(neginf.sum()),
        "below_min": int(below.sum()),
        "above_max": int(above.sum()),
    }
    return clean.astype(np.float32, copy=False), counts


def _in_range(x: np.ndarray, lo: float, hi: float | None) -> bool:
    """Whether `x` needs no repair: two passes instead of sanitize's ten, for the common clean layer.
    min and max are NaN if any value is, and +-Inf if any value is, so finite extremes in range mean
    every value is finite and in range."""
    if x.size == 0:
        return True
    least, most = x.min(), x.max()
    return bool(np.isfinite(least) and np.isfinite(most) and least >= lo and (hi is None or most <= hi))
