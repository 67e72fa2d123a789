"""Image quality metrics, each defined once (the report prints these docstrings), and the tone map.

All metrics compare a result `x` with a reference `ref`, both (H, W, 3) linear HDR radiance.
Non-finite values are replaced by 0 first (NONFINITE_RULE), so a denoiser that emits them is scored
(badly) instead of crashing the evaluation or vanishing from it.

The evaluation scores NumPy images; training's validation scores batches of tensors. `relmse_torch`,
`psnr_torch` and `one_minus_ssim_torch` are the same definitions per sample of an (N, C, H, W) batch, side by
side with the NumPy ones so they cannot drift apart (tests/test_metrics.py compares them). HDR-FLIP has no twin and
validation leaves it out: NVIDIA's implementation costs ~25x SSIM's time (benchmarks/bench_metrics.py).
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from dataclasses import dataclass

import flip_evaluator
import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import correlate1d
from torch import Tensor

RELMSE_EPS = 1e-2
GAMMA = 2.2
PSNR_CAP_DB = 100.0
SSIM_SIGMA = 1.5
SSIM_RADIUS = 5  # 11x11 window: int(3.5 * 1.5 + 0.5), as scikit-image and Wang et al. 2004
SSIM_K1, SSIM_K2 = 0.01, 0.03
LDR_RANGE = 255.0  # PSNR and SSIM run on 8-bit values 0..255
SSIM_FLOOR_DRAWS = 2  # a 256x256 image's SSIM map averages ~200k values: two draws agree to ~1 %
NONFINITE_RULE = (
    "NaN and +-inf values in an image or its reference are replaced by 0 before every metric "
    "and counted; the count is reported next to the scores."
)


def count_nonfinite(x: np.ndarray) -> int:
    """Number of NaN or infinite values (not pixels: each channel counts)."""
    return int(np.size(x) - np.count_nonzero(np.isfinite(x)))


def finite(x: np.ndarray) -> np.ndarray:
    """float64 copy of `x` with NaN and +-inf replaced by 0 (the rule every metric applies)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(np.isfinite(x), x, 0.0)


def _check_pair(x: np.ndarray, ref: np.ndarray) -> None:
    if np.shape(x) != np.shape(ref):
        raise ValueError(f"image and reference differ in shape: {np.shape(x)} vs {np.shape(ref)}")
    if np.ndim(x) != 3 or np.shape(x)[0] == 0 or np.shape(x)[1] == 0:
        raise ValueError(f"images must be non-empty (H, W, C) arrays, got shape {np.shape(x)}")


def relmse(x: np.ndarray, ref: np.ndarray) -> float:
    """relMSE = mean over pixels and channels of (x - ref)^2 / (ref^2 + 0.01), on linear HDR values.

    The paper's "RMSE" column. The authors' code multiplies by an extra 0.5 and works on log-domain
    tensors; here there is no 0.5 factor and the images are linear radiance. Lower is better.
    """
    _check_pair(x, ref)
    x, ref = finite(x), finite(ref)
    return float(np.mean((x - ref) ** 2 / (ref**2 + RELMSE_EPS)))


def reference_floor(variance: np.ndarray, ref: np.ndarray) -> float:
    """Reference floor = mean over pixels and channels of var / (ref^2 + 0.01): the relMSE that the
    reference itself is expected to have against the converged image, from the renderer's variance of
    each pixel's mean (diffuse_var + specular_var; their covariance is left out).

    Every method's relMSE is measured against this noisy reference, so its expectation is its error
    against the converged image plus about this floor: differences below the floor are the reference's
    noise, not the method's, and "relMSE - floor" estimates the error against the converged image.
    """
    _check_pair(variance, ref)
    variance, ref = finite(variance), finite(ref)
    return float(np.mean(np.maximum(variance, 0.0) / (ref**2 + RELMSE_EPS)))


def to_ldr(x: np.ndarray) -> np.ndarray:
    """8-bit display image: round(255 * clip(max(x, 0) ^ (1/2.2), 0, 1)) as uint8 (the authors' eval)."""
    x = np.maximum(finite(x), 0.0) ** (1.0 / GAMMA)
    return np.rint(np.clip(x, 0.0, 1.0) * LDR_RANGE).astype(np.uint8)


def reinhard(x: np.ndarray) -> np.ndarray:
    """x / (1 + x) on max(x, 0): compresses HDR highlights before to_ldr, to eyeball patches side by side."""
    x = np.maximum(finite(x), 0.0)
    return x / (1.0 + x)


def psnr(x: np.ndarray, ref: np.ndarray) -> float:
    """PSNR = 10 log10(255^2 / MSE) in dB on the 8-bit images to_ldr(x), to_ldr(ref), MSE over all
    pixels and channels; capped at 100 dB (identical images would give +inf). Higher is better.
    """
    _check_pair(x, ref)
    mse = np.mean((to_ldr(x).astype(np.float64) - to_ldr(ref).astype(np.float64)) ** 2)
    if mse == 0:
        return PSNR_CAP_DB
    return float(min(10.0 * np.log10(LDR_RANGE**2 / mse), PSNR_CAP_DB))


def _gaussian_taps(radius: int) -> np.ndarray:
    taps = np.exp(-0.5 * np.arange(-radius, radius + 1) ** 2 / SSIM_SIGMA**2)
    return taps / taps.sum()


def _ssim_channel(a: np.ndarray, b: np.ndarray) -> float:
    radii = [min(SSIM_RADIUS, (n - 1) // 2) for n in a.shape]

    def blur(img: np.ndarray) -> np.ndarray:
        for axis, radius in enumerate(radii):
            img = correlate1d(img, _gaussian_taps(radius), axis=axis, mode="reflect")
        return img

    mu_a, mu_b = blur(a), blur(b)
    var_a = blur(a * a) - mu_a**2
    var_b = blur(b * b) - mu_b**2
    cov = blur(a * b) - mu_a * mu_b
    c1, c2 = (SSIM_K1 * LDR_RANGE) ** 2, (SSIM_K2 * LDR_RANGE) ** 2
    s = ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    inner = s[radii[0] : s.shape[0] - radii[0], radii[1] : s.shape[1] - radii[1]]
    return float(inner.mean(dtype=np.float64))


def ssim(x: np.ndarray, ref: np.ndarray) -> float:
    """SSIM (Wang et al. 2004) on the 8-bit images to_ldr(x), to_ldr(ref), averaged over channels.

    Gaussian window 11x11 with sigma 1.5 (population statistics, K1 = 0.01, K2 = 0.03, data range
    255, reflected borders), mean of the SSIM map without the window's radius strip at the borders:
    identical to scikit-image's structural_similarity(gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=255). An image narrower than 11 pixels along an axis gets
    a window shrunk along that axis to the largest odd size that fits (same sigma, taps renormalised);
    a 1-pixel axis thus compares single pixels. The table reports 1 - SSIM: lower is better.
    """
    _check_pair(x, ref)
    a, b = to_ldr(x).astype(np.float64), to_ldr(ref).astype(np.float64)
    return float(np.mean([_ssim_channel(a[..., c], b[..., c]) for c in range(a.shape[2])]))


def one_minus_ssim(x: np.ndarray, ref: np.ndarray) -> float:
    """1 - ssim(x, ref): the paper's SSIM column, oriented so that lower is better like relMSE."""
    return 1.0 - ssim(x, ref)


def ssim_floor(variance: np.ndarray, ref: np.ndarray) -> float:
    """SSIM floor = 1-SSIM(ref + n, ref), n ~ N(0, variance) per pixel and channel (a fixed seed, the mean of
    SSIM_FLOOR_DRAWS draws): about the 1-SSIM that the converged image itself would score against this
    noisy reference, from the renderer's variance of each pixel's mean.

    A denoiser's output is smooth where the reference is still noisy, and SSIM's structure term counts
    that noise as a flaw of the output: at high spp most of a good denoiser's 1-SSIM can be the
    reference's. Unlike relMSE, SSIM does not add up, so there is no "1-SSIM - floor". The draw puts a
    second copy of the noise on the reference: where the noise is strong against SSIM's constant C2 and
    the local contrast the estimate falls short of the converged image's score (by 10 % at a standard
    deviation of 2 of the 8-bit levels), and below one level, where 8-bit rounding adds as much, it runs
    a little over it.
    """
    _check_pair(variance, ref)
    sigma, ref = np.sqrt(np.maximum(finite(variance), 0.0)), finite(ref)
    rng = np.random.default_rng(0)
    return float(
        np.mean([one_minus_ssim(ref + sigma * rng.standard_normal(ref.shape), ref) for _ in range(SSIM_FLOOR_DRAWS)])
    )


def _finite_torch(x: Tensor) -> Tensor:
    return torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)


def to_ldr_torch(x: Tensor) -> Tensor:
    """to_ldr of a tensor, as float values 0..255 (same rounding: half to even)."""
    x = _finite_torch(x).clamp(min=0) ** (1.0 / GAMMA)
    return torch.round(LDR_RANGE * torch.clamp(x, 0, 1))


def relmse_torch(x: Tensor, ref: Tensor) -> Tensor:
    """relmse of each sample of (N, C, H, W) linear images."""
    x, ref = _finite_torch(x), _finite_torch(ref)
    return ((x - ref) ** 2 / (ref**2 + RELMSE_EPS)).flatten(1).mean(1)


def psnr_torch(x: Tensor, ref: Tensor) -> Tensor:
    """psnr of each sample of (N, C, H, W) linear images, capped at PSNR_CAP_DB."""
    mse = ((to_ldr_torch(x) - to_ldr_torch(ref)) ** 2).flatten(1).mean(1)
    db = 10 * torch.log10(LDR_RANGE**2 / mse.clamp(min=1e-30))
    return torch.where(mse == 0, torch.full_like(db, PSNR_CAP_DB), db.clamp(max=PSNR_CAP_DB))


def ssim_moments_torch(a: Tensor, b: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """SSIM's local statistics of (N, C, H, W) images under its 11x11 Gaussian window, valid convolutions
    (no border): the means, the variances and the covariance (mu_a, mu_b, var_a, var_b, cov)."""
    taps = torch.from_numpy(_gaussian_taps(SSIM_RADIUS)).to(a.device, a.dtype)
    channels = a.shape[1]
    across = taps.view(1, 1, 1, -1).expand(channels, 1, 1, -1)
    down = taps.view(1, 1, -1, 1).expand(channels, 1, -1, 1)

    def blur(img: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(img, across, groups=channels), down, groups=channels)

    mu_a, mu_b = blur(a), blur(b)
    return mu_a, mu_b, blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b


def ssim_map_torch(a: Tensor, b: Tensor) -> Tensor:
    """The SSIM map of `ssim` for (N, C, H, W) images of 8-bit values (any float, differentiable), inside
    the window's radius strip: valid convolutions see no border, as `ssim` drops the strip. Both sides
    need at least 11 pixels."""
    mu_a, mu_b, var_a, var_b, cov = ssim_moments_torch(a, b)
    c1, c2 = (SSIM_K1 * LDR_RANGE) ** 2, (SSIM_K2 * LDR_RANGE) ** 2
    return ((2 * mu_a * mu_b + c1) * (2 * cov + c2)) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


def one_minus_ssim_torch(x: Tensor, ref: Tensor) -> Tensor:
    """one_minus_ssim of each sample of (N, C, H, W) linear images, at least 11x11."""
    a, b = to_ldr_torch(x.double()), to_ldr_torch(ref.double())
    return 1.0 - ssim_map_torch(a, b).mean(dim=(2, 3)).mean(1)


FLIP_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])  # linear sRGB to luminance Y, as FLIP computes it


def hdr_flip(x: np.ndarray, ref: np.ndarray) -> float:
    """HDR-FLIP (Andersson et al. 2021; NVIDIA's `flip-evaluator` with its defaults): the mean over pixels
    of the FLIP error map between ref and x, both linear HDR radiance with negatives clipped to 0.
    LDR-FLIP models how visible a difference is to a viewer at 67 pixels per degree (colour difference
    after contrast-sensitivity filtering, plus edge and point features); HDR-FLIP computes it on both
    images tone mapped with ACES at exposures from log2(m / max Y) to log2(m / median Y), about a stop
    apart (Y: the reference's luminance, m: the value ACES maps to 0.85), and keeps each pixel's largest
    error. Where half the reference or more is black, the median is taken over its lit pixels (FLIP's
    own range would be infinite and score every image 0); a black reference takes the range from x,
    and two black images score 0.
    In [0, 1]; lower is better. It sees what relMSE under-weights: a lit pattern smeared into soft
    blobs costs its edges everywhere, while fine noise around the right mean is partly masked.
    """
    _check_pair(x, ref)
    if np.shape(x)[2] != 3:
        raise ValueError(f"HDR-FLIP compares RGB images, got {np.shape(x)[2]} channels")
    x, ref = (np.ascontiguousarray(np.maximum(finite(a), 0.0), dtype=np.float32) for a in (x, ref))
    exposures = _flip_exposures(ref, x)
    if exposures is None:  # both black
        return 0.0
    _, mean, _ = flip_evaluator.evaluate(ref, x, "HDR", applyMagma=False, parameters=exposures)
    return float(mean)


def _flip_exposures(ref: np.ndarray, x: np.ndarray) -> dict[str, float] | None:
    """{} where FLIP's own exposure range (from the reference) is finite; else the range from the median
    of the reference's lit pixels, or of x's for a black reference; None when both are black."""
    luminance = ref.reshape(-1, 3) @ FLIP_LUMINANCE
    if luminance.size >= 2 and np.median(luminance) > 0:
        return {}
    lit = luminance[luminance > 0]
    if lit.size == 0:
        luminance = x.reshape(-1, 3) @ FLIP_LUMINANCE
        lit = luminance[luminance > 0]
    if lit.size == 0:
        return None
    white = _flip_white_exposure()
    return {"startExposure": white - float(np.log2(lit.max())), "stopExposure": white - float(np.log2(np.median(lit)))}


@functools.cache
def _flip_white_exposure() -> float:
    """log2 of the radiance FLIP's ACES maps to 0.85: its start exposure for an image of luminance 1."""
    white = np.ones((2, 2, 3), dtype=np.float32)
    _, _, used = flip_evaluator.evaluate(white, white, "HDR", applyMagma=False, computeMeanError=False)
    return float(used["startExposure"])


@dataclass(frozen=True)
class Metric:
    """A column of Table 1: how to compute it from (x, ref), which direction is better, its definition."""

    key: str
    label: str
    compute: Callable[[np.ndarray, np.ndarray], float]
    lower_is_better: bool
    definition: str


METRICS: tuple[Metric, ...] = (
    Metric("one_minus_ssim", "1-SSIM", one_minus_ssim, True, inspect.getdoc(ssim)),
    Metric("psnr", "PSNR", psnr, False, inspect.getdoc(psnr)),
    Metric("relmse", "relMSE", relmse, True, inspect.getdoc(relmse)),
    Metric("hdr_flip", "HDR-FLIP", hdr_flip, True, inspect.getdoc(hdr_flip)),
)


def score(x: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """Every metric of METRICS for one image, keyed by Metric.key."""
    return {m.key: float(m.compute(x, ref)) for m in METRICS}
