"""Metrics: cross-checked against scikit-image, hand-computed cases, odd sizes and non-finite input."""

import math

import flip_evaluator
import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from admc.common import metrics


def _pair(shape, seed=0, noise=0.2):
    rng = np.random.default_rng(seed)
    ref = rng.gamma(1.0, 0.5, shape).astype(np.float32)
    return (ref + rng.normal(0, noise, shape)).astype(np.float32), ref


def _from_levels(levels) -> np.ndarray:
    """Linear values whose to_ldr is exactly `levels` (inverse of the gamma 2.2 encoding)."""
    return ((np.asarray(levels, dtype=np.float64) / 255.0) ** 2.2).astype(np.float32)


@pytest.mark.parametrize("shape", [(32, 32, 3), (127, 129, 3), (11, 11, 3), (40, 17, 3), (64, 48, 3)])
def test_ssim_and_psnr_match_scikit_image(shape):
    x, ref = _pair(shape, seed=sum(shape))
    a, b = metrics.to_ldr(x), metrics.to_ldr(ref)
    expected_ssim = structural_similarity(
        a, b, gaussian_weights=True, sigma=1.5, use_sample_covariance=False, channel_axis=-1, data_range=255
    )
    assert metrics.ssim(x, ref) == pytest.approx(expected_ssim, abs=1e-6)
    assert metrics.psnr(x, ref) == pytest.approx(peak_signal_noise_ratio(b, a, data_range=255), abs=1e-6)
    assert 0.0 < metrics.ssim(x, ref) < 0.99


def test_relmse_hand_computed():
    ref = np.array([[[0.0, 1.0, 10.0]]], dtype=np.float32)
    x = np.array([[[0.1, 2.0, 10.0]]], dtype=np.float32)
    # (0.1^2 / 0.01 + 1 / 1.01 + 0) / 3, no 0.5 factor
    expected = (0.01 / 0.01 + 1.0 / 1.01 + 0.0) / 3.0
    assert metrics.relmse(x, ref) == pytest.approx(expected, rel=1e-6)
    assert metrics.relmse(ref, ref) == 0.0
    assert metrics.relmse(np.full((4, 4, 3), 3.0), np.full((4, 4, 3), 1.0)) == pytest.approx(4.0 / 1.01)


def test_to_ldr_clips_gamma_encodes_and_quantises():
    x = np.array([[[-1.0, 0.0, 0.5], [1.0, 100.0, np.nan]]], dtype=np.float32)
    ldr = metrics.to_ldr(x)
    assert ldr.dtype == np.uint8
    assert ldr.tolist() == [[[0, 0, round(255 * 0.5 ** (1 / 2.2))], [255, 255, 0]]]


def test_psnr_hand_computed_and_capped():
    ref = _from_levels(np.full((8, 8, 3), 100))
    x = _from_levels(np.full((8, 8, 3), 101))
    assert metrics.psnr(x, ref) == pytest.approx(10 * math.log10(255**2 / 1.0), abs=1e-9)
    assert metrics.psnr(ref, ref) == metrics.PSNR_CAP_DB == 100.0
    assert metrics.ssim(ref, ref) == pytest.approx(1.0)


def test_ssim_of_one_pixel_is_the_luminance_term():
    """A 1x1 image has no variance: SSIM reduces to (2ab + C1) / (a^2 + b^2 + C1) per channel."""
    ref = _from_levels([[[50, 120, 200]]])
    x = _from_levels([[[60, 100, 200]]])
    c1 = (0.01 * 255) ** 2
    expected = np.mean([(2 * a * b + c1) / (a * a + b * b + c1) for a, b in ((60, 50), (100, 120), (200, 200))])
    assert metrics.ssim(x, ref) == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 5, 3), (10, 300, 3), (127, 129, 3), (37, 4000, 3)])
def test_odd_sizes_give_finite_scores(shape):
    x, ref = _pair(shape, seed=3)
    scores = metrics.score(x, ref)
    assert all(math.isfinite(v) for v in scores.values())
    assert 0.0 < scores["one_minus_ssim"] < 2.0
    assert 0.0 < scores["hdr_flip"] < 1.0
    assert metrics.score(ref, ref) == {
        "one_minus_ssim": pytest.approx(0.0, abs=1e-12),
        "psnr": 100.0,
        "relmse": 0.0,
        "hdr_flip": 0.0,
    }


def test_nonfinite_values_score_as_zero_and_are_counted():
    x, ref = _pair((16, 16, 3), seed=5)
    broken = x.copy()
    broken[0, 0, 0], broken[3, 4, :], broken[7, 7, 1] = np.nan, np.inf, -np.inf
    zeroed = x.copy()
    zeroed[0, 0, 0], zeroed[3, 4, :], zeroed[7, 7, 1] = 0.0, 0.0, 0.0
    assert metrics.count_nonfinite(broken) == 5
    assert metrics.score(broken, ref) == metrics.score(zeroed, ref)
    assert all(math.isfinite(v) for v in metrics.score(broken, ref).values())


def test_mismatched_shapes_raise():
    with pytest.raises(ValueError, match="differ in shape"):
        metrics.relmse(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))
    with pytest.raises(ValueError, match="non-empty"):
        metrics.psnr(np.zeros((0, 4, 3)), np.zeros((0, 4, 3)))


def test_metric_table_carries_definitions_and_directions():
    by_key = {m.key: m for m in metrics.METRICS}
    assert list(by_key) == ["one_minus_ssim", "psnr", "relmse", "hdr_flip"]
    assert by_key["psnr"].lower_is_better is False
    assert by_key["relmse"].lower_is_better and by_key["one_minus_ssim"].lower_is_better
    assert "0.5" in by_key["relmse"].definition and "100 dB" in by_key["psnr"].definition
    assert "sigma 1.5" in by_key["one_minus_ssim"].definition
    assert by_key["hdr_flip"].lower_is_better and "ACES" in by_key["hdr_flip"].definition


def _stripes(width=128, height=64, period=32, dark=0.5) -> np.ndarray:
    """Vertical lit stripes on a dimmer ground: a texture a projector light would cast."""
    lit = (np.arange(width) // (period // 2)) % 2 == 0
    return np.broadcast_to(np.where(lit, 1.0, dark)[None, :, None], (height, width, 3)).astype(np.float32).copy()


def test_hdr_flip_sees_a_smeared_pattern_that_relmse_ranks_better_than_noise():
    """The stripes smeared into soft blobs (a Gaussian of 6 pixels across them) against the same stripes
    with 27 % multiplicative noise: relMSE calls the noisy image worse, HDR-FLIP the smeared one."""
    ref = _stripes()
    smeared = gaussian_filter(ref, (0, 6.0, 0), mode="wrap").astype(np.float32)
    noisy = (ref * (1 + 0.27 * np.random.default_rng(0).normal(size=ref.shape))).astype(np.float32)
    assert metrics.relmse(noisy, ref) > metrics.relmse(smeared, ref)
    assert metrics.hdr_flip(smeared, ref) > 1.1 * metrics.hdr_flip(noisy, ref)
    assert metrics.hdr_flip(ref, ref) == 0.0


def test_hdr_flip_is_flips_own_mean_error_and_exposure_range_on_an_ordinary_image():
    x, ref = _pair((40, 56, 3), seed=11, noise=0.1)
    x = np.maximum(x, 0.0)
    _, mean, used = flip_evaluator.evaluate(ref, x, "HDR", applyMagma=False)
    assert metrics.hdr_flip(x, ref) == mean
    luminance = ref.reshape(-1, 3) @ metrics.FLIP_LUMINANCE
    assert used["startExposure"] == pytest.approx(metrics._flip_white_exposure() - np.log2(luminance.max()), abs=1e-5)


def test_hdr_flip_of_a_mostly_black_reference_is_not_zero():
    """FLIP's own exposure range ends at the median luminance: infinite when most of the reference is black
    (a small object on a black background), and every image would score 0."""
    ref = _stripes()
    ref[:, :80] = 0.0
    x = ref * 1.5
    _, mean, used = flip_evaluator.evaluate(ref, x, "HDR", applyMagma=False)
    assert mean == 0.0 and not np.isfinite(used["stopExposure"])  # why the rule exists
    assert metrics.hdr_flip(x, ref) > 0.05
    assert metrics.hdr_flip(ref, ref) == 0.0
    black = np.zeros_like(ref)
    assert metrics.hdr_flip(ref, black) > 0.2 and metrics.hdr_flip(black, ref) > 0.2  # 38 % of it is lit
    assert metrics.hdr_flip(black, black) == 0.0


def _batch(seed=0, shape=(9, 7, 3)):
    """(N, H, W, C) float64 pairs with highlights, exact matches and a NaN: what validation scores."""
    pairs = [_pair(shape, seed=seed + i) for i in range(3)]
    x = np.stack([p[0] for p in pairs]).astype(np.float64)
    ref = np.stack([p[1] for p in pairs]).astype(np.float64)
    x[0, :2] *= 40.0  # beyond 1: clipped by the tone map, not by relMSE
    x[1] = ref[1]  # identical: PSNR capped, relMSE 0
    x[2, 4, 3, 1] = np.nan  # the non-finite rule applies on both sides
    return x, ref


def test_torch_metrics_equal_numpy_ones_per_sample():
    """Validation (torch, per sample) and evaluation (NumPy, per image) compute the same numbers."""
    import torch

    x, ref = _batch()
    tx, tref = torch.from_numpy(x).permute(0, 3, 1, 2), torch.from_numpy(ref).permute(0, 3, 1, 2)
    np.testing.assert_array_equal(
        metrics.to_ldr_torch(tx).permute(0, 2, 3, 1).numpy(),
        np.stack([metrics.to_ldr(v) for v in x]).astype(np.float64),
    )
    relmse, psnr = metrics.relmse_torch(tx, tref).tolist(), metrics.psnr_torch(tx, tref).tolist()
    for i in range(len(x)):
        # float64 on both sides; only the summation order differs
        assert relmse[i] == pytest.approx(metrics.relmse(x[i], ref[i]), rel=1e-12)
        assert psnr[i] == pytest.approx(metrics.psnr(x[i], ref[i]), rel=1e-12)
    assert psnr[1] == metrics.PSNR_CAP_DB and relmse[1] == 0.0


def test_torch_ssim_equals_the_numpy_one_per_sample():
    import torch

    x, ref = _batch(shape=(17, 13, 3))
    tx, tref = torch.from_numpy(x).permute(0, 3, 1, 2), torch.from_numpy(ref).permute(0, 3, 1, 2)
    ssim_error = metrics.one_minus_ssim_torch(tx, tref).tolist()
    for i in range(len(x)):
        # float64 on both sides; scipy's separable correlation and torch's conv2d sum in other orders
        assert ssim_error[i] == pytest.approx(metrics.one_minus_ssim(x[i], ref[i]), abs=1e-12)
    assert ssim_error[1] == 0.0 and min(ssim_error[0], ssim_error[2]) > 0.01


def test_reinhard_compresses_highlights_before_the_tone_map():
    x = np.array([[[0.0, 1.0, 3.0], [-2.0, np.inf, np.nan]]])
    assert metrics.reinhard(x).tolist() == [[[0.0, 0.5, 0.75], [0.0, 0.0, 0.0]]]
    assert metrics.to_ldr(metrics.reinhard(x))[0, 0].tolist() == [
        0,
        round(255 * 0.5 ** (1 / 2.2)),
        round(255 * 0.75 ** (1 / 2.2)),
    ]


@pytest.mark.parametrize("sigma", [0.003, 0.007])
def test_ssim_floor_estimates_the_converged_images_score_against_a_noisy_reference(sigma):
    """A flat grey truth and a reference of it with Gaussian noise: ssim_floor, from the reference and its
    variance alone, against 1-SSIM(truth, reference). In 8-bit display units the noise has variance
    v = (255 / 2.2 * t^(1/2.2 - 1) * sigma)^2 and rounding adds q = 1/12 to each noisy image, so per window
    the truth's loss is (v + q) / (v + q + C2) and the draw's (v + 2q) / (3v + 2q + C2) (its image carries the
    reference's noise twice): their ratio, within the spread of the draws (3 %: ~8k windows of 3 channels)."""
    rng = np.random.default_rng(3)
    truth = np.full((96, 96, 3), 0.2)
    reference = truth + sigma * rng.standard_normal(truth.shape)
    variance = np.full(truth.shape, sigma**2)
    v, q, c2 = (255 / 2.2 * 0.2 ** (1 / 2.2 - 1) * sigma) ** 2, 1 / 12, (0.03 * 255) ** 2
    expected = (v + 2 * q) / (3 * v + 2 * q + c2) / ((v + q) / (v + q + c2))
    ratio = metrics.ssim_floor(variance, reference) / metrics.one_minus_ssim(truth, reference)
    assert ratio == pytest.approx(expected, abs=0.03), v


def test_ssim_floor_of_a_noiseless_reference_is_zero():
    ref = np.random.default_rng(0).uniform(0, 1, (32, 32, 3))
    assert metrics.ssim_floor(np.zeros_like(ref), ref) == 0.0
