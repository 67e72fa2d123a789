"""Exposure normalisation: dim images are denoised at the trained brightness and scaled back, dark regions
again at a higher exposure (CPU)."""

import numpy as np
import pytest
import torch
from torch import nn

from test_inference import log_tolerance, render_layers, strong_generator
from test_unet import strong_unet
from admc.model.inference.denoiser import FullImageDenoiser
from admc.model.inference.exposure import dark_region
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.exposure import (
    DARK_GAIN,
    DARK_LEVEL,
    TRAINED_BRIGHTNESS,
    brightness,
    dark_weights,
    exposure_gain,
)
from admc.model.transforms import RADIANCE_MAX, diffuse_forward, specular_forward


def denoiser(normalize: bool, dtype: torch.dtype, dark_pass: bool = True) -> FullImageDenoiser:
    return FullImageDenoiser(
        strong_generator(1),
        strong_generator(2),
        DenoiserOptions(dtype=dtype, normalize_exposure=normalize, dark_pass=dark_pass),
    )


def scaled(layers: dict, factor: float) -> dict:
    return {k: v * np.float32(factor) if k in ("diffuse", "specular") else v for k, v in layers.items()}


def test_brightness_is_the_lit_pixels_geometric_mean():
    image = np.zeros((4, 4, 3), np.float32)
    image[:2] = 0.05
    image[2, 0] = 0.2  # geometric mean of eight 0.05 and one 0.2 pixel
    assert brightness(image) == pytest.approx(np.exp((8 * np.log(0.05) + np.log(0.2)) / 9), rel=1e-5)
    assert brightness(np.zeros((3, 3, 3), np.float32)) == 0.0


def test_only_dim_images_get_a_gain_and_never_past_the_radiance_limit():
    bright = np.full((4, 4, 3), 2.0, np.float32)
    assert exposure_gain(bright) == 1.0
    assert exposure_gain(np.zeros_like(bright)) == 1.0
    dim = np.full((4, 4, 3), 0.01, np.float32)
    assert exposure_gain(dim) == 16.0  # 0.21 / 0.01 = 21: the nearest power of two
    dim[0, 0] = RADIANCE_MAX / 5  # a directly seen emitter: scaled by more than 4 it would be clipped
    assert exposure_gain(dim) == 4.0


def test_a_dim_image_denoises_the_same_at_any_exposure(inference_dtype):
    layers = scaled(render_layers(24, 20, seed=3), 0.01)
    assert brightness(layers["diffuse"] + layers["specular"]) < TRAINED_BRIGHTNESS / 8
    normalized, plain = denoiser(True, inference_dtype), denoiser(False, inference_dtype)
    once, darker = normalized(layers), normalized(scaled(layers, 1 / 8))
    assert once.exposure_gain > 1 and darker.exposure_gain == 8 * once.exposure_gain
    np.testing.assert_array_equal(darker.image * 8, once.image)  # powers of two: the very same values
    assert any("dim image" in note for note in once.notes)
    once, darker = plain(layers), plain(scaled(layers, 1 / 8))  # without it, the output is not proportional
    assert not np.allclose(darker.image * 8, once.image, rtol=1e-2, atol=0)


def test_bright_images_and_environment_pixels_are_untouched(inference_dtype):
    layers = render_layers(16, 16, seed=4)
    assert brightness(layers["diffuse"] + layers["specular"]) > TRAINED_BRIGHTNESS
    np.testing.assert_array_equal(
        denoiser(True, inference_dtype)(layers).image, denoiser(False, inference_dtype)(layers).image
    )
    dim = scaled(layers, 0.001)
    dim["coverage"] = np.ones((16, 16, 1), np.float32)
    dim["coverage"][:, :5] = 0.0  # environment: passed through, whatever the gain
    result = denoiser(True, inference_dtype)(dim)
    assert result.exposure_gain > 1
    np.testing.assert_allclose(result.image[:, :5], (dim["diffuse"] + dim["specular"])[:, :5], rtol=1e-5)


def test_dark_weights_follow_log_luminance_and_skip_the_environment():
    levels = np.array([1.0, DARK_LEVEL, DARK_LEVEL / 8, DARK_LEVEL / DARK_GAIN, 1e-6, 0.0], np.float32)
    image = np.repeat(np.repeat(levels[:, None, None], 40, 1), 3, 2)  # flat rows, far apart for the blur
    image = np.repeat(image, 40, 0)
    coverage = np.ones((*image.shape[:2], 1), np.float32)
    coverage[-40:] = 0.0  # the black row is environment
    weights = dark_weights(image, 1.0, coverage)[20::40, 20, 0]  # each row's centre
    np.testing.assert_allclose(weights, [0.0, 0.0, 0.5, 1.0, 1.0, 0.0], atol=1e-6)  # 3 of 6 stops: half
    np.testing.assert_array_equal(dark_weights(image / 8, 8.0, coverage), dark_weights(image, 1.0, coverage))


class LogOffset(nn.Module):
    """A real module with a fixed log-domain error: +0.001 on every output, at any exposure."""

    def forward(self, noisy, features):
        return noisy + 0.001


def offset_denoiser(dark_pass: bool) -> FullImageDenoiser:
    """float32: an addition runs in float32 under autocast too (only convs and matmuls go to bf16)."""
    return FullImageDenoiser(
        LogOffset(),
        LogOffset(),
        DenoiserOptions(overlap=0, dtype=torch.float32, normalize_exposure=False, dark_pass=dark_pass),
    )


def test_dark_regions_come_from_the_brighter_pass_and_bright_images_run_once():
    layers = render_layers(24, 24, seed=5)
    for name in ("diffuse", "specular"):
        layers[name][:, :12] *= np.float32(1e-4)  # a dark left half
        layers[name][:, 12:] += np.float32(1.0)  # a bright right half
    twice, once = offset_denoiser(True)(layers), offset_denoiser(False)(layers)
    brighter = offset_denoiser(False)(scaled(layers, DARK_GAIN))
    weights = dark_weights(once.image, 1.0, layers["coverage"])
    assert (weights[:, :6] == 1).all() and (weights[:, -6:] == 0).all()
    assert twice.dark_share == pytest.approx(float(weights.mean()))
    for branch in ("diffuse", "specular"):  # each branch blended with the same weights
        first, second = getattr(once, branch), getattr(brighter, branch) / DARK_GAIN
        np.testing.assert_array_equal(getattr(twice, branch), first + weights * (second - first))
    np.testing.assert_array_equal(twice.image[:, -6:], once.image[:, -6:])
    noisy = layers["diffuse"] + layers["specular"]
    dark_error, plain_error = np.abs(twice.image - noisy)[:, :6], np.abs(once.image - noisy)[:, :6]
    assert dark_error.max() < plain_error.min() / 32  # the same log-domain error, 64x less radiance
    bright = render_layers(16, 16, seed=6)
    bright["diffuse"] += np.float32(1.0)  # nothing dark: one pass, the same image
    result = offset_denoiser(True)(bright)
    assert result.dark_share == 0.0
    np.testing.assert_array_equal(result.image, offset_denoiser(False)(bright).image)


@pytest.mark.parametrize("backbone", ["residual", "unet"])
def test_the_dark_pass_runs_on_the_dark_region_only_and_equals_a_whole_image_pass(backbone, inference_dtype):
    """A dark corner: the second pass runs on its bounding box plus the networks' halo (in tiles, at that;
    for the multi-scale body starting on its coarse grid), and the result equals blending a whole-image
    pass at DARK_GAIN x the exposure."""
    height, width, top, left = (70, 90, 50, 60) if backbone == "residual" else (96, 128, 80, 110)
    layers = render_layers(height, width, seed=7)
    for name in ("diffuse", "specular"):
        layers[name] += np.float32(1.0)
        layers[name][top:, left:] *= np.float32(1e-4)  # the bottom-right corner is dark

    def generator(seed: int):
        return strong_generator(seed, scale=0.7) if backbone == "residual" else strong_unet(seed)

    def make(dark_pass: bool) -> FullImageDenoiser:
        return FullImageDenoiser(
            generator(1),
            generator(2),
            DenoiserOptions(
                tile=16 if backbone == "residual" else 32,
                dtype=inference_dtype,
                normalize_exposure=False,
                dark_pass=dark_pass,
            ),
        )

    twice, once = make(True)(layers), make(False)(layers)
    brighter = make(False)(scaled(layers, DARK_GAIN))  # the whole image at the second pass's exposure
    weights = dark_weights(once.image, 1.0, layers["coverage"])
    rows, cols = dark_region(weights, make(True).overlap, make(True).alignment)
    assert 0 < rows.start < top and rows.stop == height and 0 < cols.start < left and cols.stop == width
    assert not weights[: rows.start].any() and not weights[:, : cols.start].any()
    albedo = layers["albedo"]
    for branch, forward in (("diffuse", lambda x: diffuse_forward(x, albedo)), ("specular", specular_forward)):
        first, second = getattr(once, branch), getattr(brighter, branch) / DARK_GAIN
        expected = first + weights * (second - first)
        # crops and tiles differ by log_tolerance in the log domain; back in linear units at 1/DARK_GAIN
        # that is up to tolerance * (v + (albedo + eps) / DARK_GAIN) on a value v
        magnitude = max(np.abs(forward(getattr(run, branch))).max() for run in (once, brighter))
        tolerance = log_tolerance(inference_dtype, magnitude)
        np.testing.assert_allclose(getattr(twice, branch), expected, rtol=2 * tolerance, atol=2 * tolerance / DARK_GAIN)
    corner = np.abs(twice.image - once.image)[top:, left:] / (np.abs(once.image[top:, left:]) + 1e-3)
    assert float(corner.max()) > 1e-2  # the check can fail: the second pass changed the corner


def test_dark_region_starts_on_the_generators_grid():
    weights = np.zeros((40, 50, 1), np.float32)
    weights[21:23, 30:31] = 0.5
    assert dark_region(weights, 3, 1) == (slice(18, 26), slice(27, 34))
    assert dark_region(weights, 3, 8) == (slice(16, 26), slice(24, 34))
    assert dark_region(weights, 30, 8) == (slice(0, 40), slice(0, 50))
