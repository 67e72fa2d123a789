"""Keep what the input already resolves: where a render is nearly converged and the network's output
departs from it by more than the render's own noise explains, move the output back toward the input.

A network trained on smooth procedural irradiance smears detail it never saw (a projected pattern, a
hard shadow) even where the render resolves it, and then does worse than its own input at high spp.
The render's variance of each pixel's mean, v, says how far the input x can be from the converged
image; the output d has an error b the network does not report. Taking d + w (x - d) has expected
error (1 - w)^2 b^2 + w^2 v, least at w = b^2 / (b^2 + v). b^2 is estimated per pixel from the window
around it: mean (d - x)^2 is b^2 + v when d's error is independent of x's noise, so b^2 is what exceeds
the window's mean v, counted only beyond MARGIN standard errors of that mean. Both are taken relative
to the pixel's value (as relMSE weighs errors), so a firefly does not swamp its window.

At low spp that estimate is noise: the network's error is a few percent of v and no window is large
enough to see it. So w is used only where the input is nearly converged (its window's relative variance
below CONVERGED), and is 0 elsewhere: there the output is the network's, bit for bit. A variance of 0 is
no proof of convergence: at low spp every sample of a pixel may miss a small light alike, so a window
whose pixels all report no variance is not taken as resolved either. One that also holds sampled pixels
is judged on theirs: a low-spp miss sits among pixels whose rare hits make the window's variance huge,
while silent pixels beside resolved ones are dark (a ceiling beside a ceiling light, with no diffuse
light at all), and a network that bleeds light into them is taken back.

Chosen on the out-of-family set (eval.split = "ood": 12 scenes, 256x256) and on 12 in-family scenes of
corpus.seed 0, never on a test image, from window radii 2-6, margins 0-12, CONVERGED 1e-3-2e-2 and
UNSAMPLED 0-0.25 (docs/results/2026-12-02-keep-resolved.md). With these values admc's relMSE, 1-SSIM and
HDR-FLIP out of family moved by 1.9%, 2.5% and 0.7% less error at 64 spp, removing both cells where it
had been worse than its input, by at most 0.4% on any image at 4 and 16 spp; in family by under 0.1%.
UNSAMPLED went from 0.25 to all but one pixel on the same two sets (docs/results/2026-12-03-broad-finetune-blend.md):
admc+oidn's relMSE out of family 1.078x -> 1.029x and 1.122x -> 0.960x OIDN's at 16 and 64 spp, no image
worse by more than 0.12% on any metric, in family within 0.1%.
It costs one box filter per branch, a second where any window is below CONVERGED and a third where one is
resolved.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter

from admc.common.metrics import RELMSE_EPS

RADIUS = 4
"""Half the window edge over which the bias and the variance are averaged (9x9 pixels)."""
MARGIN = 8.0
"""How many standard errors of the window's mean squared difference b^2 must exceed before it counts."""
CONVERGED = 1e-2
"""Relative variance of the mean (v / (value^2 + RELMSE_EPS), window mean) below which an input counts as resolved:
a relative standard error of about 10%."""
UNSAMPLED = 1.0 - 0.5 / (2 * RADIUS + 1) ** 2
"""The largest share of a window's pixels with a variance of 0 for which it can count as resolved: all but
one. A window of silent pixels alone says nothing; one that also holds sampled pixels of low variance is
a converged region whose silent pixels are dark."""


def keep_resolved(
    denoised: np.ndarray, noisy: np.ndarray, variance: np.ndarray, value: np.ndarray
) -> tuple[np.ndarray, float]:
    """(output, mean weight of the input): `denoised` moved toward `noisy` where the input is resolved.

    All (H, W, 3) float32 and finite: one branch's output, its sanitised input and the variance of the
    input's mean; `value` (H, W, 3) is the denoised final image, whose brightness makes errors relative.
    Pixels with weight 0 keep `denoised` exactly.
    """
    size = 2 * RADIUS + 1
    scale = np.square(_channel_mean(value)) + np.float32(RELMSE_EPS)  # as relMSE: dark pixels are not blown up
    mean_variance = np.maximum(uniform_filter(_channel_mean(variance) / scale, size, mode="reflect"), 0.0)
    resolved = mean_variance < CONVERGED
    if not resolved.any():  # most of a low-spp image: nothing more to compute
        return denoised, 0.0
    silent = (variance[..., 0] <= 0) & (variance[..., 1] <= 0) & (variance[..., 2] <= 0)
    resolved &= uniform_filter(silent.astype(np.float32), size, mode="reflect") <= UNSAMPLED
    if not resolved.any():
        return denoised, 0.0
    mean_squared = uniform_filter(_channel_mean(np.square(denoised - noisy)) / scale, size, mode="reflect")
    bias = mean_squared - mean_variance * np.float32(1.0 + MARGIN * np.sqrt(2.0) / size)
    weight = np.where((bias > 0) & resolved, bias / np.maximum(bias + mean_variance, 1e-30), 0.0)
    weight = np.clip(weight, 0.0, 1.0).astype(np.float32)[..., None]
    if not weight.any():
        return denoised, 0.0
    return denoised + weight * (noisy - denoised), float(weight.mean())


def _channel_mean(image: np.ndarray) -> np.ndarray:
    """(H, W) mean of the three channels: three plain adds, several times faster than a mean over the last axis."""
    return (image[..., 0] + image[..., 1] + image[..., 2]) * np.float32(1.0 / 3.0)
