"""Data transforms between rendered buffers and network tensors (NumPy HWC float arrays in and out).

Radiance goes into a log domain so that HDR values fit FP16 with even relative precision; diffuse is
first demodulated by albedo (the network sees texture-free illumination, as in the authors' code).
Features are mapped to [0, 1]. Inputs are sanitised first (admc.common.buffers.sanitize, counted and
reported by the caller); the forward transforms refuse anything non-finite, so nothing passes on silently.
"""

from __future__ import annotations

import numpy as np
import torch

from admc.common.buffers import DENOISER_LAYERS, LAYERS, RADIANCE_MAX, VARIANCE_MAX, sanitize
from admc.common.layout import FEATURE_CHANNELS, FP16_MAX

EPS = 0.00316
"""Added to albedo before demodulating diffuse (value from the authors' code)."""

SPEC_VERSION = 1


def transform_spec() -> dict:
    """Every transform and parameter, JSON-ready: stored in the patch store, checked by models."""
    return {
        "version": SPEC_VERSION,
        "eps": EPS,
        "radiance_max": RADIANCE_MAX,
        "fp16_max": FP16_MAX,
        "sanitize": {
            name: {"nan": LAYERS[name].nan, "min": LAYERS[name].low, "max": LAYERS[name].high}
            for name in DENOISER_LAYERS
        },
        "diffuse": "log1p(clip(diffuse, 0, radiance_max) / (albedo + eps)), albedo = clip(albedo, 0, 1)",
        "diffuse_inverse": "expm1(d) * (albedo + eps)",
        "specular": "log1p(clip(specular, 0, radiance_max))",
        "specular_inverse": "expm1(s)",
        "normal": "clip((nan_to_0(n) + 1) / 2, 0, 1)",
        "depth": "depth / max(depth over hits of the whole image); hit = coverage > 0 and depth > 0 "
        "and finite; other pixels 1.0; no hits: all 1.0",
        "albedo": "clip(nan_to_0(albedo), 0, 1)",
        "feature_channels": list(FEATURE_CHANNELS),
    }


def _require_finite(func: str, **arrays: np.ndarray) -> None:
    for name, a in arrays.items():
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        if bad:
            raise ValueError(f"{func}: {name} has {bad} non-finite values; call sanitize({name!r}) first")


def _log1p_(x: np.ndarray) -> np.ndarray:
    """log1p of a float32 array the caller owns, in place, through torch: NumPy's float32 log1p and expm1
    are scalar loops, torch's are vectorised (a 1280x720 RGB layer: 56 against 7 ms on an AVX2 CPU)."""
    x = np.asarray(x)  # a NumPy scalar (what ufuncs return for 0-d input) as a 0-d array
    torch.from_numpy(x).log1p_()
    return x


def _expm1_(x: np.ndarray) -> np.ndarray:
    """expm1 in place, as _log1p_."""
    x = np.asarray(x)
    torch.from_numpy(x).expm1_()
    return x


def _demodulation_albedo(albedo: np.ndarray) -> np.ndarray:
    """Albedo as used to (de)modulate diffuse: the same clipped values as the albedo feature."""
    return np.clip(np.asarray(albedo, dtype=np.float32), 0.0, 1.0) + np.float32(EPS)


def diffuse_forward(diffuse: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """log1p(diffuse / (albedo + eps)) on finite inputs, in float32: the clip keeps the quotient below
    RADIANCE_MAX / EPS (2.1e7), far inside float32's range, and float64 would only change the last bit
    of values the network reads in bf16 (and the patch store keeps in FP16)."""
    _require_finite("diffuse_forward", diffuse=diffuse, albedo=albedo)
    d = np.clip(np.asarray(diffuse, dtype=np.float32), 0.0, RADIANCE_MAX)
    return _log1p_(d / _demodulation_albedo(albedo))


def diffuse_inverse(d: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """expm1(d) * (albedo + eps): linear diffuse radiance from the log domain."""
    _require_finite("diffuse_inverse", d=d, albedo=albedo)
    linear = _expm1_(np.array(d, dtype=np.float32))
    linear *= _demodulation_albedo(albedo)
    return linear


def specular_forward(specular: np.ndarray) -> np.ndarray:
    """log1p(specular) on finite inputs, negatives to 0."""
    _require_finite("specular_forward", specular=specular)
    return _log1p_(np.clip(np.asarray(specular, dtype=np.float32), 0.0, RADIANCE_MAX))


def specular_inverse(s: np.ndarray) -> np.ndarray:
    """expm1(s): linear specular radiance from the log domain."""
    _require_finite("specular_inverse", s=s)
    return _expm1_(np.array(s, dtype=np.float32))


def normal_forward(normal: np.ndarray) -> np.ndarray:
    """Shading normals from [-1, 1] to [0, 1], sanitised first: NaN ends at 0.5, +-Inf at 1 or 0."""
    return (sanitize(normal, "normal")[0] + np.float32(1.0)) * np.float32(0.5)


def depth_forward(depth: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """Depth / (max depth over the whole image's hits); environment pixels 1.0 (infinitely far).

    Call on the whole image before tiling, so training patches and full-image inference share one
    scale. A hit is coverage > 0 with a finite depth > 0; an image without hits is all 1.0.
    """
    depth = np.asarray(depth, dtype=np.float32)
    coverage = np.asarray(coverage, dtype=np.float32)
    if depth.shape != coverage.shape:
        raise ValueError(f"depth_forward: depth shape {depth.shape} != coverage shape {coverage.shape}")
    hit = (coverage > 0) & np.isfinite(depth) & (depth > 0)
    if not hit.any():
        return np.ones_like(depth)
    scale = np.float64(depth[hit].max())
    out = np.ones(depth.shape, dtype=np.float32)
    out[hit] = np.clip(depth[hit] / scale, 0.0, 1.0)
    return out


def albedo_forward(albedo: np.ndarray) -> np.ndarray:
    """Albedo sanitised: clipped to [0, 1], NaN -> 0."""
    return sanitize(albedo, "albedo")[0]


def features(normal: np.ndarray, depth: np.ndarray, albedo: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """The 7 feature channels (H, W, 7) in the authors' order: normal(3), depth(1), albedo(3)."""
    if normal.shape[-1] != 3 or albedo.shape[-1] != 3 or depth.shape[-1] != 1:
        raise ValueError(
            f"features: expected normal (H,W,3), depth (H,W,1), albedo (H,W,3); got "
            f"{normal.shape}, {depth.shape}, {albedo.shape}"
        )
    return np.concatenate([normal_forward(normal), depth_forward(depth, coverage), albedo_forward(albedo)], axis=-1)


def to_fp16(x: np.ndarray) -> tuple[np.ndarray, int]:
    """Cast to float16, clamping values beyond +-65504 first (counted) so no Inf is ever produced.

    NaN is refused: it must have been sanitized, not cast.
    """
    x = np.asarray(x, dtype=np.float32)
    nan = int(np.isnan(x).sum())
    if nan:
        raise ValueError(f"to_fp16: {nan} NaN values; sanitize before casting")
    beyond = np.abs(x) > FP16_MAX
    n_clamped = int(beyond.sum())
    if n_clamped:
        x = np.clip(x, -FP16_MAX, FP16_MAX)
    return x.astype(np.float16), n_clamped


# model.noise_input: each branch's per-pixel noise level, from the renders' variance buffers. Not part of
# transform_spec (weights without the input never read it; a store keeps it only with tile.noise_maps).

NOISE_STD_UNIT = 1e-3
"""The noise map's unit: a standard deviation of 0.001 in the log domain, about what a 64-spp studio
render's flat regions carry. The map is log1p(std / unit) / log1p(1 / unit)."""


def noise_forward(variance: np.ndarray, radiance: np.ndarray, scale: np.ndarray | float) -> np.ndarray:
    """One branch's per-pixel noise level (H, W, 1) in its own log domain, for model.noise_input.

    `variance` is the render's variance of the pixel mean of `radiance` (both linear, (H, W, 3));
    `scale` is what the log domain divides by: albedo + eps for diffuse, 1 for specular. By the delta
    method, d log1p(x / s) = dx / (x + s), so the standard deviation the network's input carries is
    std = sqrt(variance) / (radiance + s), averaged over RGB. The map is logarithmic in it,
    log1p(std / NOISE_STD_UNIT) / log1p(1 / NOISE_STD_UNIT): 0 where converged, 1 at std 1, and a step
    of ~0.1 per halving in between, so 4 and 64 spp differ by a signal the size of the other features'
    (a linear map of std, mostly below 0.05, gives a weight that starts at 0 almost nothing to learn
    from). NaN and negative variances count as 0.
    """
    var = np.nan_to_num(np.asarray(variance, dtype=np.float64), nan=0.0, posinf=VARIANCE_MAX, neginf=0.0)
    x = np.nan_to_num(np.asarray(radiance, dtype=np.float64), nan=0.0, posinf=RADIANCE_MAX, neginf=0.0)
    std = np.sqrt(np.clip(var, 0.0, VARIANCE_MAX)) / (np.clip(x, 0.0, RADIANCE_MAX) + scale)
    level = np.log1p(std.mean(axis=-1, keepdims=True) / NOISE_STD_UNIT) / np.log1p(1.0 / NOISE_STD_UNIT)
    return level.astype(np.float32)


def diffuse_noise(variance: np.ndarray, diffuse: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """noise_forward for the diffuse branch (its log domain divides by albedo + eps)."""
    return noise_forward(variance, diffuse, _demodulation_albedo(albedo))


def specular_noise(variance: np.ndarray, specular: np.ndarray) -> np.ndarray:
    """noise_forward for the specular branch (log1p: a scale of 1)."""
    return noise_forward(variance, specular, 1.0)
