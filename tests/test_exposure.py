"""Exposure normalisation: dim images are denoised at the trained brightness and scaled back (CPU)."""
import numpy as np
import pytest
import torch

from test_inference import render_layers, strong_generator
from admc.model.exposure import TRAINED_BRIGHTNESS, brightness, exposure_gain
from admc.model.inference import FullImageDenoiser
from admc.model.transforms import RADIANCE_MAX

def denoiser(normalize: bool) -> FullImageDenoiser:
    return FullImageDenoiser(strong_generator(1), strong_generator(2), dtype=torch.float32,
                             normalize_exposure=normalize)


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


def test_a_dim_image_denoises_the_same_at_any_exposure():
    layers = scaled(render_layers(24, 20, seed=3), 0.01)
    assert brightness(layers["diffuse"] + layers["specular"]) < TRAINED_BRIGHTNESS / 8
    normalized, plain = denoiser(True), denoiser(False)
    once, darker = normalized(layers), normalized(scaled(layers, 1 / 8))
    assert once.exposure_gain > 1 and darker.exposure_gain == 8 * once.exposure_gain
    np.testing.assert_array_equal(darker.image * 8, once.image)  # powers of two: the very same values
    assert any("dim image" in note for note in once.notes)
    once, darker = plain(layers), plain(scaled(layers, 1 / 8))  # without it, the output is not proportional
    assert not np.allclose(darker.image * 8, once.image, rtol=1e-2, atol=0)


def test_bright_images_and_environment_pixels_are_untouched():
    layers = render_layers(16, 16, seed=4)
    assert brightness(layers["diffuse"] + layers["specular"]) > TRAINED_BRIGHTNESS
    np.testing.assert_array_equal(denoiser(True)(layers).image, denoiser(False)(layers).image)
    dim = scaled(layers, 0.001)
    dim["coverage"] = np.ones((16, 16, 1), np.float32)
    dim["coverage"][:, :5] = 0.0  # environment: passed through, whatever the gain
    result = denoiser(True)(dim)
    assert result.exposure_gain > 1
    np.testing.assert_allclose(result.image[:, :5], (dim["diffuse"] + dim["specular"])[:, :5], rtol=1e-5)
