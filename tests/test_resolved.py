"""Keeping what the input resolves (model/inference/resolved.py): a smeared pattern the render resolves comes
back, a noisy input or an unbiased output is left to the network, and the denoiser applies it only with
the variance layers."""

import numpy as np
import torch
from torch import nn

from admc.model.inference.denoiser import FullImageDenoiser
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.resolved import keep_resolved

SIZE = 64


def stripes() -> np.ndarray:
    """Converged radiance with a pattern of 2-px stripes (a projector's) on a level of 1."""
    row = np.where(np.arange(SIZE) % 4 < 2, 1.5, 0.5).astype(np.float32)
    return np.repeat(np.broadcast_to(row[None, :, None], (SIZE, SIZE, 1)), 3, axis=2).copy()


def render(truth: np.ndarray, variance: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A noisy render of `truth` whose pixel means have this variance, and its variance layer."""
    noise = np.random.default_rng(seed).normal(0.0, np.sqrt(variance), truth.shape).astype(np.float32)
    return truth + noise, np.full(truth.shape, variance, np.float32)


def mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((a - b) ** 2))


def test_a_resolved_pattern_the_output_smeared_comes_back():
    truth = stripes()
    noisy, variance = render(truth, 1e-4, seed=0)
    smeared = np.ones_like(truth)
    out, share = keep_resolved(smeared, noisy, variance, smeared)
    assert share > 0.9
    assert mse(out, truth) < 0.05 * mse(smeared, truth)
    assert mse(out, truth) < 2 * mse(noisy, truth)  # about the input's own error, not more


def fireflies(seed: int, chance: float, spp: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """A low-spp render of a level of 1 where a sample finds a light of 1 / `chance` with that chance: each
    pixel's mean of `spp` samples and the variance of that mean estimated from them, as the renderer
    writes it (0 where every sample missed)."""
    samples = np.where(np.random.default_rng(seed).random((spp, SIZE, SIZE, 3)) < chance, 1.0 / chance, 0.0)
    return (samples.mean(axis=0).astype(np.float32), (samples.var(axis=0, ddof=1) / spp).astype(np.float32))


def test_a_low_spp_input_leaves_the_output_exactly_as_the_network_gave_it():
    """At 4 spp the network's error is a few percent of the input's variance, and the heavy-tailed samples
    make every window's estimate of it noise: only a resolved input may be kept."""
    truth = np.ones((SIZE, SIZE, 3), np.float32)
    for seed, chance in [(0, 0.1), (1, 0.1), (2, 0.01), (3, 0.01)]:  # 0.01: most pixels report no variance
        noisy, variance = fireflies(seed, chance)
        for output in (truth, np.full_like(truth, 0.9)):  # exact, and 10% off: neither can be told here
            out, share = keep_resolved(output, noisy, variance, output)
            assert share == 0.0
            np.testing.assert_array_equal(out, output)


def test_a_noisy_input_with_blotchy_noise_leaves_the_output_as_the_network_gave_it():
    """Noise correlated over 8-px blocks (sample patterns, bounced light found alike by neighbours): a 9x9
    window holds about two independent values, so its mean squared difference says little about a
    bias. Only an input whose variance says it is resolved may be kept."""
    truth = np.ones((SIZE, SIZE, 3), np.float32)
    for seed in range(3):
        blocks = np.random.default_rng(seed).normal(0.0, 0.5, (SIZE // 8, SIZE // 8, 3)).astype(np.float32)
        noisy = truth + np.kron(blocks, np.ones((8, 8, 1), np.float32))
        out, share = keep_resolved(truth, noisy, np.full_like(truth, 0.25), truth)
        assert share == 0.0
        np.testing.assert_array_equal(out, truth)


def test_an_unbiased_output_of_a_nearly_resolved_input_is_kept():
    truth = np.ones((SIZE, SIZE, 3), np.float32)
    noisy, variance = render(truth, 4e-3, seed=2)  # resolved (relative variance < 1e-2), still noisy
    out, share = keep_resolved(truth, noisy, variance, truth)
    assert share < 0.01  # (d - x)^2 is the input's noise: no evidence of a bias beyond the margin
    assert mse(out, truth) < 0.01 * mse(noisy, truth)


def test_light_bled_into_silent_pixels_beside_a_resolved_light_is_taken_back():
    """A ceiling beside a ceiling light gets no direct light: its diffuse samples are all 0 (variance 0),
    and a network that bleeds the light into it adds error no input showed (OOD scene ood-200000002). A
    window that holds sampled, resolved pixels besides silent ones counts as resolved; a window of silent
    pixels alone says nothing (every sample may have missed a small light) and is left as it was."""
    noisy = np.zeros((SIZE, SIZE, 3), np.float32)
    noisy[:2] = 20.0  # the light: every sample sees it, relative variance of the mean 5e-3
    variance = np.where(noisy > 0, np.float32(2.0), np.float32(0.0))
    bled = noisy.copy()
    bled[:2] = 17.0
    bled[2:12] = 1.0  # the light smeared 10 rows into the silent ceiling
    out, share = keep_resolved(bled, noisy, variance, bled)
    assert share > 0
    assert np.abs(out[2:4]).max() < 0.05  # beside the light: back to the input's 0
    assert np.abs(out[:2] - 20.0).max() < np.abs(bled[:2] - 20.0).max()
    np.testing.assert_array_equal(out[2 + 4 :], bled[2 + 4 :])  # 9x9 windows without the light: as given


class Smear(nn.Module):
    """A real module that returns its log-domain input averaged over the image: it removes every detail."""

    def forward(self, noisy, features):
        return noisy.mean(dim=(2, 3), keepdim=True).expand_as(noisy).clone()


def pattern_layers(variance: float | None) -> dict[str, np.ndarray]:
    truth = stripes()
    noisy, var = render(truth, variance or 1e-4, seed=3)
    layers = {
        "diffuse": noisy,
        "albedo": np.ones_like(noisy),
        "normal": np.tile(np.float32([0, 0, 1]), (SIZE, SIZE, 1)),
        "depth": np.ones((SIZE, SIZE, 1), np.float32),
    }
    if variance is not None:
        layers["diffuse_var"] = var
    return layers


def test_the_denoiser_keeps_resolved_detail_only_with_the_variance_layer_and_the_option():
    def make(keep: bool) -> FullImageDenoiser:
        return FullImageDenoiser(Smear(), None, DenoiserOptions(overlap=0, dtype=torch.float32, keep_resolved=keep))

    layers = pattern_layers(1e-4)
    plain, kept = make(False)(layers), make(True)(layers)
    truth = stripes()
    assert plain.resolved_share == 0.0 and kept.resolved_share > 0.9
    assert mse(kept.image, truth) < 0.05 * mse(plain.image, truth)
    assert any("resolved" in note for note in kept.notes)
    assert "keeps resolved input" in make(True).device
    without = pattern_layers(None)  # a user's EXR without variance layers: the network's output as it is
    np.testing.assert_array_equal(make(True)(without).image, make(False)(without).image)
    assert make(True)(without).resolved_share == 0.0
