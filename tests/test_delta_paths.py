"""Pixels that see the environment only through mirrors or smooth glass (issue 34, item 4): real renders of a
mirror sphere under an environment map, the integrator's features there and the shipped weights on them.

Before, every sample of such a pixel escaped without reaching a non-delta vertex, so the pixel had coverage 0,
no normal and no depth, and inference passed it through as if it showed the environment directly.
"""
from pathlib import Path

import numpy as np
import pytest

from admc.common.metrics import relmse
from admc.model.inference import load_denoiser, sanitize_layers
from admc.model.oidn_base import oidn_bases
from admc.pipeline.render.integrator import render_buffers

SIZE = 32
WEIGHTS = Path(__file__).resolve().parents[1] / "weights"
MIRROR = 0.8  # the sphere's reflectance: a perfect mirror ("material": "none") scaled by it


def _sky(mi) -> "mi.Bitmap":
    """A lat-long environment with detail a curved mirror turns into per-pixel noise: a gradient and a checker."""
    theta, phi = np.meshgrid(np.linspace(0, np.pi, 32), np.linspace(0, 2 * np.pi, 64), indexing="ij")
    checker = (np.floor(theta * 6 / np.pi) + np.floor(phi * 6 / np.pi)) % 2
    value = 0.3 + 0.5 * np.cos(theta) ** 2 + 1.5 * checker
    return mi.Bitmap(np.stack([value, 0.8 * value, 0.6 * value], axis=-1).astype(np.float32))


def _sphere_scene(mi, bsdf: dict):
    """A unit sphere at the origin seen from z = 4 filling the image's middle, the environment around it."""
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": SIZE, "height": SIZE, "rfilter": {"type": "box"}}},
        "sky": {"type": "envmap", "bitmap": _sky(mi)},
        "ball": {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
    })


MIRROR_BSDF = {"type": "conductor", "material": "none", "specular_reflectance": {"type": "rgb", "value": MIRROR}}
CENTRE = (slice(SIZE // 2 - 1, SIZE // 2 + 1),) * 2  # the 2x2 pixels around the image centre


@pytest.fixture(scope="module")
def mirror(variant):
    """The mirror sphere at 4 spp and its 256-spp reference."""
    import mitsuba as mi

    scene = _sphere_scene(mi, MIRROR_BSDF)
    reference = render_buffers(scene, 256, seed=99)
    return render_buffers(scene, 4, seed=1), reference["diffuse"] + reference["specular"]


@pytest.mark.parametrize("bsdf", [MIRROR_BSDF, {"type": "dielectric"}], ids=["mirror", "glass"])
def test_environment_seen_through_a_delta_surface_is_covered_with_its_old_features(variant, bsdf):
    """Every sample of the sphere's pixels escapes to the environment after the sphere: coverage 1 (it was
    0), and the features the networks were trained on there: no normal, no depth, the chain's throughput."""
    import mitsuba as mi

    layers = render_buffers(_sphere_scene(mi, bsdf), 4, seed=0)
    assert np.all(layers["coverage"][CENTRE] == 1)
    assert np.all(layers["normal"][CENTRE] == 0) and np.all(layers["depth"][CENTRE] == 0)
    if bsdf is MIRROR_BSDF:
        np.testing.assert_allclose(layers["albedo"][CENTRE], MIRROR, rtol=1e-6)
    sky = layers["coverage"][..., 0] == 0
    assert sky[0, 0] and sky.sum() > SIZE * SIZE // 3  # the environment seen directly: unchanged
    assert np.all(layers["normal"][sky] == 0) and np.all(layers["depth"][sky] == 0)
    assert np.all(layers["albedo"][sky] == 1)


def _sphere_and_sky(layers):
    """Pixels wholly on the sphere and wholly on the environment, told apart by albedo (0.8 and 1) rather than
    by the coverage whose meaning is under test."""
    albedo = layers["albedo"][..., 0]
    return np.isclose(albedo, MIRROR, rtol=1e-6), albedo == 1


def test_admc_denoises_the_mirror_instead_of_passing_it_through(mirror):
    layers, _ = mirror
    noisy = layers["diffuse"] + layers["specular"]
    out = load_denoiser(WEIGHTS / "admc-small-pretrained.pt")(layers).image
    sphere, sky = _sphere_and_sky(layers)
    changed = np.abs(out - noisy) > 1e-3 * noisy
    assert changed[sphere].mean() > 0.9
    np.testing.assert_allclose(out[sky], noisy[sky], rtol=1e-6)  # the environment seen directly is kept


def test_the_refiner_keeps_oidn_on_the_environment_and_refines_it_on_the_mirror(mirror):
    layers, reference = mirror
    out = load_denoiser(WEIGHTS / "admc-small-refiner.pt")(layers).image
    clean, _ = sanitize_layers(layers)
    bases = oidn_bases({name: clean[name] for name in ("diffuse", "specular", "albedo", "normal")})
    base = bases["diffuse"] + bases["specular"]
    sphere, sky = _sphere_and_sky(layers)
    # the log transform and its inverse round trip in float32
    np.testing.assert_allclose(out[sky], base[sky], rtol=1e-5, atol=1e-6)
    noisy = layers["diffuse"] + layers["specular"]
    assert np.abs(base[sky] - noisy[sky]).max() > 1e-3  # OIDN does change them: the check can fail
    # On the mirror the refiner corrects OIDN by well under 1 % (either way, seed by seed: 0.992x to 1.004x over
    # 8 seeds); the issue's bound for it is 2 % over OIDN. Passing the noisy input through was 1.22x.
    error, base_error = (relmse(image[sphere][None], reference[sphere][None]) for image in (out, base))
    assert error <= 1.02 * base_error
