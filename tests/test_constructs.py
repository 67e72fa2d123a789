"""The corpus's named constructs, each rendered for real (32x32, 4 spp unless said) in a probe scene:
a grey floor and a sphere, lit only by what the test adds. Every check compares against the same
scene with the construct's defining feature taken out, so it fails if the construct lost it."""

import numpy as np
import pytest

from admc.pipeline.render import integrator
from admc.pipeline.render.scenes import CONSTRUCTS, FAMILIES, SceneError, SceneSpec, procedural_corpus, scene_hash
from admc.pipeline.render.scenes.constructs import Aim, choose_constructs
from admc.pipeline.render.scenes.geometry import UP, look_at, planar
from admc.pipeline.render.scenes.loading import load_description, plain_description
from admc.pipeline.render.scenes.plain import Image
from admc.pipeline.render.scenes.staging import new_scene, rgb
from admc.pipeline.render.scenes.textures import checker

EYE, TARGET = np.array([0.0, 1.2, 1.6]), np.array([0.0, 0.15, 0.0])


def probe(floor=None, environment=None, ball=True) -> tuple[dict, Aim]:
    scene = new_scene((32, 32), EYE, TARGET, 45.0)
    scene["floor"] = {
        "type": "rectangle",
        "to_world": planar([0, 0, 0], UP, [0, 0, -1], 1.5, 1.5),
        "bsdf": floor or {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": rgb([0.5] * 3)}},
    }
    if ball:
        scene["ball"] = {
            "type": "sphere",
            "center": TARGET.tolist(),
            "radius": 0.15,
            "bsdf": {"type": "diffuse", "reflectance": rgb([0.6, 0.5, 0.4])},
        }
    if environment is not None:
        scene["environment"] = environment
    return scene, Aim(EYE, TARGET, 0.4, 0.0, 1.0)


def with_construct(name: str, seed: int = 0, **probe_args) -> dict:
    scene, aim = probe(**probe_args)
    CONSTRUCTS[name].add(np.random.default_rng(seed), scene, aim)
    return scene


def render(scene: dict, spp: int = 4, seed: int = 0) -> dict[str, np.ndarray]:
    return integrator.render_buffers(load_description(scene), spp, seed, split=True)


def luminance(buffers: dict) -> np.ndarray:
    image = buffers["diffuse"] + buffers["specular"]
    return image @ np.array([0.2126, 0.7152, 0.0722])


def detail(image: np.ndarray) -> float:
    """Mean absolute difference between neighbouring pixels over the mean: what a pattern adds."""
    return float(
        (np.abs(np.diff(image, axis=0)).mean() + np.abs(np.diff(image, axis=1)).mean()) / (image.mean() + 1e-9)
    )


def light_key(scene: dict) -> str:
    return next(key for key in ("projector", "spot") if key in scene)


def test_projector_and_spot_lights_draw_their_slide_inside_the_lit_region(variant):
    kinds = set()
    for seed in range(4):
        scene = with_construct("projector", seed)
        key = light_key(scene)
        kinds.add(key)
        flat = dict(scene)
        texture_key = "irradiance" if key == "projector" else "texture"
        slide = scene[key][texture_key]["bitmap"].pixels
        uniform = Image(np.broadcast_to(slide.reshape(-1, 3).mean(0), slide.shape).copy())
        flat[key] = dict(scene[key], **{texture_key: dict(scene[key][texture_key], bitmap=uniform)})
        patterned, plain = luminance(render(scene)), luminance(render(flat))
        assert patterned.mean() > 0.02
        assert detail(patterned) > 1.5 * detail(plain), (seed, key)
    assert kinds == {"projector", "spot"}


@pytest.mark.parametrize("name", ["grate", "foliage"])
def test_occluders_cast_hard_high_frequency_shadows(variant, name):
    scene = with_construct(name)
    assert scene[name]["bsdf"]["type"] == "mask"
    open_sky = {key: value for key, value in scene.items() if key != name}
    shadowed, lit = luminance(render(scene)), luminance(render(open_sky))
    assert 0.15 * lit.mean() < shadowed.mean() < 0.9 * lit.mean()  # the card's holes let part of the light through
    assert detail(shadowed) > 1.5 * detail(lit)


def test_hdr_sky_has_a_hard_sun_that_casts_a_sharp_shadow(variant):
    scene = with_construct("hdr_sky")
    sky = scene["environment"]["bitmap"].pixels
    brightness = sky.mean(-1)
    assert brightness.max() > 100 * np.median(brightness)  # a sun, not a glow
    assert (brightness > 0.5 * brightness.max()).mean() < 1e-3  # a few pixels of a 128x256 map
    no_sun = sky.copy()
    no_sun[brightness > 50 * np.median(brightness)] = np.median(sky.reshape(-1, 3), axis=0)
    overcast = dict(scene, environment=dict(scene["environment"], bitmap=Image(no_sun)))
    sunny, dull = luminance(render(scene, spp=16)), luminance(render(overcast, spp=16))
    contrast = lambda image: np.percentile(image, 95) / max(np.percentile(image, 5), 1e-6)  # noqa: E731
    assert sunny.mean() > 1.3 * dull.mean()
    assert contrast(sunny) > contrast(dull)


GRAZING = {"type": "point", "position": [1.5, 0.4, 0.0], "intensity": rgb([8.0] * 3)}


def test_bump_and_normal_maps_ripple_the_shading_under_a_grazing_light(variant):
    """Radiance, not the normal buffer: Mitsuba perturbs the frame inside the BSDF, so the features'
    shading normal does not see a bump or normal map (a gap in the features, not in the corpus)."""
    seen = set()
    for seed in range(4):
        scene = dict(with_construct("bump", seed, ball=False), grazing=GRAZING)
        seen.add(scene["floor"]["bsdf"]["bsdf"]["type"])
        bumped, smooth = luminance(render(scene)), luminance(render(dict(probe(ball=False)[0], grazing=GRAZING)))
        assert detail(bumped) > 1.5 * detail(smooth), seed
    assert seen == {"bumpmap", "normalmap"}


def test_textured_roughness_changes_a_highlight_beyond_noise(variant):
    """The floor reflects a small light towards the camera: patches of sharp and blurred highlight under
    a textured roughness differ from the blob under its mean roughness by far more than the noise."""
    light = {
        "type": "sphere",
        "center": [0.0, 1.0, -1.0],
        "radius": 0.05,
        "emitter": {"type": "area", "radiance": rgb([300.0] * 3)},
    }
    for seed in range(2):
        scene = dict(with_construct("rough_texture", seed, ball=False), light=light)
        metal = scene["floor"]["bsdf"]["bsdf"]
        alpha = metal["alpha"]["bitmap"].pixels
        assert metal["type"] == "roughconductor" and alpha.max() - alpha.min() > 0.1
        uniform = dict(
            scene, floor=dict(scene["floor"], bsdf={"type": "twosided", "bsdf": dict(metal, alpha=float(alpha.mean()))})
        )
        textured, plain, plain_again = (
            render(s, spp=64, seed=k)["specular"].sum(-1) for s, k in ((scene, 0), (uniform, 0), (uniform, 1))
        )
        assert textured.mean() > 0.01
        assert np.abs(textured - plain).mean() > 3.0 * np.abs(plain - plain_again).mean(), seed


def fine_checker(checks: int = 16) -> Image:
    u = (np.arange(128) + 0.5) / 128
    mask = (np.floor(u * checks)[:, None] + np.floor(u * checks)[None, :]) % 2
    return Image(np.repeat((0.1 + 0.7 * mask)[..., None], 3, -1))


def test_thin_lens_blurs_what_is_out_of_focus(variant):
    """Neighbour contrast of a fine checker floor drops under the thin lens by more than it varies
    between two seeds of the pinhole render (0.3 % here; the blur takes 2-11 % off)."""
    floor = {
        "type": "twosided",
        "bsdf": {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": fine_checker()}},
    }
    environment = {"type": "constant", "radiance": rgb([1.0] * 3)}
    blurred_sum = sharp_sum = 0.0
    for seed in range(3):
        scene = with_construct("thinlens", seed, floor=floor, environment=environment)
        assert scene["sensor"]["type"] == "thinlens" and scene["sensor"]["aperture_radius"] > 0
        pinhole = dict(scene, sensor=dict(scene["sensor"], type="perspective"))
        del pinhole["sensor"]["aperture_radius"], pinhole["sensor"]["focus_distance"]
        blurred = detail(luminance(render(scene, spp=64)))
        sharp, sharp_again = (detail(luminance(render(pinhole, spp=64, seed=k))) for k in (0, 1))
        assert blurred < min(sharp, sharp_again), seed
        blurred_sum, sharp_sum = blurred_sum + blurred, sharp_sum + sharp
    assert blurred_sum < 0.95 * sharp_sum


def test_mirrors_and_glass_show_the_environment_where_the_floor_is_black(variant):
    """Under a checker sky with a black floor and no ball, a pixel below the horizon is lit only if its
    path meets mirrors or glass (delta surfaces) and then the sky."""
    black = {"type": "diffuse", "reflectance": rgb([0.0] * 3)}
    environment = {"type": "envmap", "bitmap": checker(np.random.default_rng(2)), "scale": 2.0}
    for seed in range(3):
        scene = with_construct("mirrors", seed, floor=black, environment=environment, ball=False)
        optics = {
            value["bsdf"]["type"] for key, value in scene.items() if key.startswith("optic_") and key != "optic_panel"
        }
        assert optics and optics <= {"conductor", "dielectric"}
        with_optics = luminance(render(scene))
        without = luminance(render(probe(floor=black, environment=environment, ball=False)[0]))
        assert ((with_optics > 0.05) & (without == 0.0)).sum() >= 3, seed


def test_caustic_focuses_the_small_light_through_glass_into_the_balls_shadow(variant):
    """The floor in the shadow an opaque ball would cast (under 5 % of the open floor's light) gets a
    fifth or more of it back through glass: the glass passes ~90 % (Fresnel), some of the caustic may
    land outside that shadow, and 256 spp estimate it within tens of percent. 256 spp and a camera zoomed
    onto the ball: at 4 spp a path-traced caustic is a few fireflies (what the corpus wants the denoiser to
    see, not what a test can measure)."""
    for seed in range(2):
        scene = with_construct("caustic", seed, ball=False)
        glass = scene["caustic_glass"]
        assert glass["bsdf"]["type"] == "dielectric" and scene["caustic_light"]["radius"] <= 0.05
        scene["sensor"] = dict(
            scene["sensor"], fov=25.0, to_world=look_at(EYE, [glass["center"][0], 0.0, glass["center"][2]])
        )
        opaque = dict(scene, caustic_glass=dict(glass, bsdf={"type": "diffuse", "reflectance": rgb([0.0] * 3)}))
        bare = {key: value for key, value in scene.items() if key != "caustic_glass"}
        lit, dark, open_floor = (render(s, spp=256) for s in (scene, opaque, bare))
        floor_seen = np.abs(dark["depth"] - open_floor["depth"])[..., 0] < 1e-3
        shadow = floor_seen & (luminance(dark) < 0.05 * luminance(open_floor))
        assert shadow.sum() >= 10, seed
        assert luminance(lit)[shadow].sum() > 0.2 * luminance(open_floor)[shadow].sum(), seed


# ------------------------------------------------------------------------------ mixing and seeds


def test_constructs_mix_into_families_on_their_own_stream():
    """With construct_chance 0 a corpus is exactly as before; with it, the scenes without constructs
    are still the same scenes, and those with them say so in their id."""
    plain = procedural_corpus(["room", "tabletop", "studio", "preview"], 16, seed=1, resolution=(32, 32))
    mixed = procedural_corpus(
        ["room", "tabletop", "studio", "preview"],
        16,
        seed=1,
        resolution=(32, 32),
        constructs=tuple(CONSTRUCTS),
        construct_chance=0.6,
    )
    assert all(not spec.constructs for spec in plain)
    assert 4 <= sum(bool(spec.constructs) for spec in mixed) <= 15
    for before, after in zip(plain, mixed):
        assert after.scene_id == before.scene_id + "".join(f"+{name}" for name in after.constructs)
        if not after.constructs:
            assert scene_hash(after) == scene_hash(before)
    assert not any("caustic" in spec.constructs for spec in mixed if spec.family == "studio")  # nothing to stand on


def test_every_construct_is_reachable_from_every_family_that_can_hold_it():
    for family in ("room", "tabletop", "studio", "preview"):
        drawn = {
            name
            for seed in range(200)
            for name in choose_constructs(family, seed, tuple(CONSTRUCTS), 1.0, FAMILIES[family].has_support)
        }
        expected = {name for name, c in CONSTRUCTS.items() if FAMILIES[family].has_support or not c.needs_support}
        assert drawn == expected, family


@pytest.mark.parametrize("family", ["room", "tabletop", "studio", "preview"])
def test_a_family_with_every_construct_renders_a_sane_image(variant, family):
    names = tuple(n for n, c in CONSTRUCTS.items() if FAMILIES[family].has_support or not c.needs_support)
    spec = SceneSpec("all", family, 5, (32, 32), constructs=names)
    image = luminance(render(plain_description(spec)))
    assert np.isfinite(image).all() and 0.005 < image.mean() < 20.0


def test_an_unknown_construct_in_a_spec_is_named():
    with pytest.raises(SceneError, match=r"unknown constructs \['laser'\]"):
        plain_description(SceneSpec("x", "room", 1, (32, 32), constructs=("laser",)))
