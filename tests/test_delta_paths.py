"""Pixels that see the environment only through mirrors or smooth glass (issue 34, item 4): real renders of a
mirror sphere under an environment map, the integrator's features there and the shipped weights on them.

Before, every sample of such a pixel escaped without reaching a non-delta vertex, so the pixel had coverage 0,
no normal and no depth, and inference passed it through as if it showed the environment directly.
"""

import numpy as np
import pytest

from admc.common.metrics import relmse
from admc.model.inference.denoiser import load_denoiser
from admc.model.inference.input_layers import sanitize_layers
from admc.model.inference.options import DenoiserOptions
from admc.model.inference.oidn_base import oidn_bases
from admc.pipeline.render.integrator import render_buffers
from admc.pipeline.weights import WEIGHTS_DIR

SIZE = 32
MIRROR = 0.8  # the sphere's reflectance: a perfect mirror ("material": "none") scaled by it


def _sky(mi):
    """A lat-long environment (a mi.Bitmap) with detail a curved mirror turns into per-pixel noise: a gradient
    and a checker."""
    theta, phi = np.meshgrid(np.linspace(0, np.pi, 32), np.linspace(0, 2 * np.pi, 64), indexing="ij")
    checker = (np.floor(theta * 6 / np.pi) + np.floor(phi * 6 / np.pi)) % 2
    value = 0.3 + 0.5 * np.cos(theta) ** 2 + 1.5 * checker
    return mi.Bitmap(np.stack([value, 0.8 * value, 0.6 * value], axis=-1).astype(np.float32))


def _sphere_scene(mi, bsdf: dict, sky: dict | None = None):
    """A unit sphere at the origin seen from z = 4 filling the image's middle, the environment around it."""
    T = mi.ScalarTransform4f
    return mi.load_dict(
        {
            "type": "scene",
            "sensor": {
                "type": "perspective",
                "fov": 40,
                "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"}},
            },
            "sky": sky or {"type": "envmap", "bitmap": _sky(mi)},
            "ball": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
        }
    )


MIRROR_BSDF = {"type": "conductor", "material": "none", "specular_reflectance": {"type": "rgb", "value": MIRROR}}
CENTRE = (slice(SIZE // 2 - 1, SIZE // 2 + 1),) * 2  # the 2x2 pixels around the image centre


@pytest.fixture(scope="module")
def mirror(variant):
    """The mirror sphere at 4 spp and its 256-spp reference."""
    import mitsuba as mi

    scene = _sphere_scene(mi, MIRROR_BSDF)
    reference = render_buffers(scene, 256, seed=99)
    return render_buffers(scene, 4, seed=1), reference["diffuse"] + reference["specular"]


def _on_sphere_and_off(margin: float = 1.5):
    """Pixels wholly on the sphere's image and wholly off it: the unit sphere at distance 4 spans asin(1/4) of
    the 20-degree half field of view, a disc of radius 11.35 pixels around the centre."""
    radius = SIZE / 2 * np.tan(np.arcsin(0.25)) / np.tan(np.radians(20))
    y, x = np.mgrid[:SIZE, :SIZE] + 0.5 - SIZE / 2
    distance = np.hypot(x, y)
    return distance < radius - margin, distance > radius + margin


@pytest.mark.parametrize("bsdf", [MIRROR_BSDF, {"type": "dielectric"}], ids=["mirror", "glass"])
def test_environment_seen_through_a_delta_surface_is_covered_with_its_old_features(variant, bsdf):
    """Every sample of the sphere's pixels escapes to the environment after the sphere and they see different
    parts of the sky: coverage 1 (it was 0), with the features the networks were trained on there: no normal,
    no depth, the chain's throughput as albedo."""
    import mitsuba as mi

    layers = render_buffers(_sphere_scene(mi, bsdf), 4, seed=0)
    on, off = _on_sphere_and_off()
    coverage = layers["coverage"][..., 0]
    assert (coverage[on] == 1).mean() > 0.9  # the rest: pixels whose 4 samples saw the same sky
    assert np.all(layers["normal"] == 0) and np.all(layers["depth"] == 0)  # no non-delta surface anywhere
    if bsdf is MIRROR_BSDF:
        np.testing.assert_allclose(layers["albedo"][on], MIRROR, rtol=1e-6)
    assert np.all(coverage[off] == 0) and np.all(layers["albedo"][off] == 1)  # the environment seen directly


def test_a_uniform_sky_in_a_mirror_has_nothing_to_denoise_and_stays_environment(variant):
    """Every sample of a centre pixel sees the same sky through the same mirror: the samples agree (to float32
    rounding), there is no noise, and the pixel keeps coverage 0 to be passed through exactly."""
    import mitsuba as mi

    sky = {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 0.7, 0.3]}}
    layers = render_buffers(_sphere_scene(mi, MIRROR_BSDF, sky), 4, seed=0)
    assert np.all(layers["coverage"][CENTRE] == 0)
    np.testing.assert_allclose(
        layers["diffuse"][CENTRE], np.broadcast_to(MIRROR * np.array([1.0, 0.7, 0.3]), (2, 2, 3)), rtol=1e-6
    )


def test_admc_denoises_the_mirror_instead_of_passing_it_through(mirror, inference_dtype):
    layers, _ = mirror
    noisy = layers["diffuse"] + layers["specular"]
    out = load_denoiser(WEIGHTS_DIR / "admc-small-pretrained.pt", DenoiserOptions(dtype=inference_dtype))(layers).image
    sphere, sky = _on_sphere_and_off()
    changed = np.abs(out - noisy) > 1e-3 * noisy
    assert changed[sphere].mean() > 0.8
    np.testing.assert_allclose(out[sky], noisy[sky], rtol=1e-6)  # the environment seen directly is kept


def test_the_refiner_refines_oidn_on_the_mirror_and_keeps_the_environment_exact(mirror, inference_dtype):
    layers, reference = mirror
    noisy = layers["diffuse"] + layers["specular"]
    out = load_denoiser(WEIGHTS_DIR / "admc-small-refiner.pt", DenoiserOptions(dtype=inference_dtype))(layers).image
    clean, _ = sanitize_layers(layers)
    bases = oidn_bases({name: clean[name] for name in ("diffuse", "specular", "albedo", "normal")}, "oidn")  # its base
    base = bases["diffuse"] + bases["specular"]
    sphere, sky = _on_sphere_and_off()
    # On the mirror the refiner corrects OIDN by well under 1 % (either way, seed by seed: 0.992x to 1.004x over
    # 8 seeds; bf16 and float32 differ by 2e-5 of that); the issue's bound for it is 2 % over OIDN. Passing the
    # noisy input through was 1.22x.
    error, base_error = (relmse(image[sphere][None], reference[sphere][None]) for image in (out, base))
    assert error <= 1.02 * base_error
    # The environment seen directly has no noise: the input is exact there, OIDN's output is not (around small
    # emitters on a black void it was a halo of over 1000x the scene's relMSE), so the refiner keeps the input.
    np.testing.assert_allclose(out[sky], noisy[sky], rtol=1e-6)
    assert np.abs(base[sky] - noisy[sky]).max() > 1e-3  # OIDN does change them: the check can fail
