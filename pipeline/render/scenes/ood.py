"""The `ood` family, held out of training: layouts and constructs no training family contains.

It measures what a denoiser does on scenes unlike its training data (the out-of-family set,
`eval.split = "ood"`), so nothing here may be mixed into training: `corpus.held_out_families` keeps
the family out of `corpus.families`, and its constructs are not in `constructs.CONSTRUCTS`.

Layouts: a box lit by a small ceiling panel and a skylight (Cornell-like), or plinths of different heights
on open ground. Constructs (`OOD_CONSTRUCTS`): Mitsuba's analytic sun and sky, a directional sun
through venetian blinds (real slats), a textured emitting screen, brushed (anisotropic) metal,
frosted glass, and a texture-weighted blend of paint and metal. The k-th scene of a corpus leads
with construct (k // 2) mod 6 in layout k mod 2, so any 12 consecutive scenes hold every pair.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from . import masks, materials
from .constructs import (
    Aim,
    around_target,
    base_height,
    direction_above,
    irradiance,
    pick_shapes,
    rewrite_bsdf,
    set_bsdf,
)
from .geometry import UP, box, planar
from .plain import Image, Matrix
from .spec import SEEDS_PER_CORPUS, SceneError
from .staging import OBJECT_KINDS, Layout, exposure, family_rng, new_scene, object_material, place_object, rgb
from .textures import random_colour, random_pattern

LAYOUTS = ("box", "plinths")


# Mitsuba's sunsky has +Z up in its own frame; this turns that onto the scenes' +Y (sun_direction is in world space).
Z_UP_TO_Y_UP = Matrix(np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]))


def _sunsky(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    direction = direction_above(rng, 0.4, 1.3)
    strength = aim.scale * rng.uniform(1.0, 3.0)
    scene["environment"] = {
        "type": "sunsky",
        "to_world": Z_UP_TO_Y_UP,
        "sun_direction": direction.tolist(),
        "turbidity": rng.uniform(2.0, 8.0),
        "albedo": rng.uniform(0.1, 0.5),
        "sun_scale": strength,
        "sky_scale": strength,
    }


def _beyond(rng: np.random.Generator, aim: Aim, min_elevation: float, max_elevation: float) -> np.ndarray:
    """A direction above the target on the far side from the camera (give or take 60 degrees), so what
    a light there casts falls towards the camera and nothing placed on the way stands in front of it."""
    direction = direction_above(rng, min_elevation, max_elevation)
    away = (aim.target - np.asarray(aim.eye))[[0, 2]]
    angle = np.arctan2(away[0], away[1]) + rng.uniform(-1.0, 1.0)
    horizontal = np.hypot(direction[0], direction[2])
    return np.array([horizontal * np.sin(angle), direction[1], horizontal * np.cos(angle)])


def _blinds(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """A directional sun through horizontal slats: shadows as sharp as geometry can make them."""
    direction = -_beyond(rng, aim, 0.9, 1.3)
    scene["blinds_sun"] = {
        "type": "directional",
        "direction": direction.tolist(),
        "irradiance": rgb([irradiance(rng, aim)] * 3),
    }
    centre = aim.target + direction * rng.uniform(0.4, 0.6) / direction[1]  # 0.4-0.6 m above the target
    across = np.cross(direction, UP)
    across /= np.linalg.norm(across)
    half_width, count = 1.5 * aim.radius + 0.3, int(rng.integers(5, 12))
    spacing = 3.0 * aim.radius / count
    slat_bsdf = {
        "type": "twosided",
        "bsdf": {"type": "diffuse", "reflectance": rgb(random_colour(rng, value=(0.3, 0.8)))},
    }
    up = np.cross(across, direction)
    for index in range(count):
        middle = centre + up * (index - count / 2) * spacing
        slat = planar(
            middle, -direction + up * rng.uniform(-0.3, 0.3), across, 0.5 * spacing * rng.uniform(0.5, 0.8), half_width
        )
        scene[f"blinds_slat_{index}"] = {"type": "rectangle", "to_world": slat, "bsdf": slat_bsdf}


def _screen(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """An emitting screen with a picture on it (a TV, a lit stained-glass pane), facing the target."""
    x, z = around_target(rng, aim)
    half = rng.uniform(0.3, 0.6) * aim.radius
    centre = np.array([x, base_height(aim, half) + half * rng.uniform(1.0, 2.0), z])
    picture = np.asarray(random_pattern(rng).pixels) / 0.85  # radiance above 1: "raw" keeps Mitsuba from warning
    radiance = irradiance(rng, aim) / (np.pi * (2 * half) ** 2) * np.linalg.norm(centre - aim.target) ** 2 * 3.0
    to_target, to_eye = aim.target - centre, np.asarray(aim.eye) - centre
    facing = to_target / np.linalg.norm(to_target) + to_eye / np.linalg.norm(
        to_eye
    )  # lights the target, seen by the camera
    scene["screen"] = {
        "type": "rectangle",
        "to_world": planar(centre, facing, UP, half, half * rng.uniform(0.6, 1.0)),
        "emitter": {
            "type": "area",
            "radiance": {"type": "bitmap", "bitmap": Image(picture * radiance), "filter_type": "nearest", "raw": True},
        },
    }


def _brushed(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    for key in pick_shapes(rng, scene, 2):
        along, across = rng.uniform(0.005, 0.05), rng.uniform(0.2, 0.5)
        alpha_u, alpha_v = (along, across) if rng.uniform() < 0.5 else (across, along)
        metal = materials.METALS[int(rng.integers(len(materials.METALS)))]
        set_bsdf(
            scene,
            key,
            {
                "type": "twosided",
                "bsdf": {
                    "type": "roughconductor",
                    "distribution": "ggx",
                    "material": metal,
                    "alpha_u": alpha_u,
                    "alpha_v": alpha_v,
                },
            },
        )


def _frosted(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    for index in range(int(rng.integers(1, 3))):
        size = rng.uniform(0.2, 0.4) * aim.radius
        x, z = around_target(rng, aim)
        scene[f"frosted_{index}"] = {
            "type": "sphere",
            "center": [x, base_height(aim, size) + size, z],
            "radius": size,
            "bsdf": {
                "type": "roughdielectric",
                "distribution": "ggx",
                "alpha": rng.uniform(0.05, 0.3),
                "int_ior": rng.uniform(1.4, 1.6),
                "ext_ior": 1.0,
            },
        }


def _patina(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """Paint worn through to metal: a blend of diffuse and rough metal weighted by a texture."""
    for key in pick_shapes(rng, scene, 2):
        weight = np.clip(masks.random_height(rng) * rng.uniform(0.8, 1.5), 0.0, 1.0)
        paint = {"type": "diffuse", "reflectance": rgb(random_colour(rng))}
        metal = {
            "type": "roughconductor",
            "distribution": "ggx",
            "alpha": rng.uniform(0.05, 0.2),
            "material": materials.METALS[int(rng.integers(len(materials.METALS)))],
        }
        rewrite_bsdf(
            scene,
            key,
            lambda inner: (
                inner
                if inner.get("type") == "dielectric"
                else {
                    "type": "blendbsdf",
                    "weight": {"type": "bitmap", "bitmap": Image(weight), "filter_type": "bilinear"},
                    "bsdf_0": paint,
                    "bsdf_1": metal,
                }
            ),
        )


OOD_CONSTRUCTS: dict[str, Callable[[np.random.Generator, dict, Aim], None]] = {
    "sunsky": _sunsky,
    "blinds": _blinds,
    "screen": _screen,
    "brushed": _brushed,
    "frosted": _frosted,
    "patina": _patina,
}
OOD_NAMES = tuple(OOD_CONSTRUCTS)  # in the order scenes lead with them


def _box_layout(rng: np.random.Generator, scene: dict, scale: float) -> Aim:
    """A 1 m box open towards the camera, coloured side walls, a small ceiling light at the front and a
    skylight (a square hole) at the back of the ceiling, which lets a sky or a sun in."""
    white = {"type": "diffuse", "reflectance": rgb([rng.uniform(0.6, 0.8)] * 3)}
    left, right = (
        random_colour(rng, saturation=(0.6, 0.9), value=(0.4, 0.7)),
        random_colour(rng, saturation=(0.6, 0.9), value=(0.4, 0.7)),
    )
    hole = rng.uniform(0.1, 0.2)  # half size; the hole spans x in [-hole, hole], z in [-0.4, -0.4 + 2 hole]
    walls = {
        "floor": ([0, 0, 0], UP, 0.5, 0.5, white),
        "back": ([0, 0.5, -0.5], [0, 0, 1], 0.5, 0.5, white),
        "left": ([-0.5, 0.5, 0], [1, 0, 0], 0.5, 0.5, {"type": "diffuse", "reflectance": rgb(left)}),
        "right": ([0.5, 0.5, 0], [-1, 0, 0], 0.5, 0.5, {"type": "diffuse", "reflectance": rgb(right)}),
        "ceiling_front": ([0, 1, (0.5 - 0.4 + 2 * hole) / 2], -UP, 0.5, (0.5 + 0.4 - 2 * hole) / 2, white),
        "ceiling_back": ([0, 1, -0.45], -UP, 0.5, 0.05, white),
        "ceiling_left": ([-(0.5 + hole) / 2, 1, -0.4 + hole], -UP, (0.5 - hole) / 2, hole, white),
        "ceiling_right": ([(0.5 + hole) / 2, 1, -0.4 + hole], -UP, (0.5 - hole) / 2, hole, white),
    }
    for name, (centre, normal, half_u, half_v, bsdf) in walls.items():
        v_direction = [0, 0, -1] if name == "floor" or name.startswith("ceiling") else UP
        # planar's local X is v x n: for the floor and ceiling pieces that is world x, so half_u spans x
        scene[f"box_{name}"] = {
            "type": "rectangle",
            "to_world": planar(centre, normal, v_direction, half_u, half_v),
            "bsdf": {"type": "twosided", "bsdf": bsdf},
        }
    half = rng.uniform(0.06, 0.12)
    radiance = rng.uniform(2.0, 4.0) * scale * np.pi / (4 * half * half) * 0.5
    scene["box_light"] = {
        "type": "rectangle",
        "to_world": planar([0, 0.999, 0.25], -UP, [0, 0, 1], half, half),
        "emitter": {"type": "area", "radiance": rgb(np.array([1.0, 0.85, 0.65]) * radiance)},
    }
    layout = Layout()
    for index in range(int(rng.integers(1, 4))):
        size = rng.uniform(0.08, 0.16)
        spot = layout.free_spot(rng, (-0.3, 0.3), (-0.3, 0.2), size)
        if spot is not None:
            kind = OBJECT_KINDS[int(rng.integers(len(OBJECT_KINDS)))]
            place_object(
                scene,
                f"item_{index}",
                rng,
                kind,
                spot[0],
                spot[1],
                0.0,
                size,
                object_material(rng, kind, materials.ALL_KINDS),
            )
    return Aim(np.array([0.0, 0.5, 1.9]), np.array([0.0, 0.3, 0.0]), 0.35, 0.0, scale)


def _plinths_layout(rng: np.random.Generator, scene: dict, scale: float) -> Aim:
    """Two to four plinths of different heights on open ground, an object on each, a soft sky."""
    scene["ground"] = {
        "type": "rectangle",
        "to_world": planar([0, 0, 0], UP, [0, 0, -1], 10.0, 10.0),
        "bsdf": {
            "type": "twosided",
            "bsdf": {"type": "diffuse", "reflectance": rgb(random_colour(rng, value=(0.3, 0.6)))},
        },
    }
    scene["environment"] = {"type": "constant", "radiance": rgb([0.3 * scale] * 3)}
    stone = {
        "type": "twosided",
        "bsdf": {"type": "diffuse", "reflectance": rgb(random_colour(rng, saturation=(0.0, 0.2), value=(0.4, 0.8)))},
    }
    count = int(rng.integers(2, 5))
    for index in range(count):
        x, height, size = (index - (count - 1) / 2) * 0.35, rng.uniform(0.1, 0.5), rng.uniform(0.07, 0.12)
        scene[f"plinth_{index}"] = {
            "type": "cube",
            "to_world": box([x, height / 2, 0.0], [0.13, height / 2, 0.13], rng.uniform(0, 30)),
            "bsdf": stone,
        }
        kind = OBJECT_KINDS[int(rng.integers(len(OBJECT_KINDS)))]
        place_object(
            scene, f"item_{index}", rng, kind, x, 0.0, height, size, object_material(rng, kind, materials.ALL_KINDS)
        )
    azimuth = rng.uniform(-0.6, 0.6)
    eye = np.array([2.2 * np.sin(azimuth), rng.uniform(0.5, 1.2), 2.2 * np.cos(azimuth)])
    return Aim(eye, np.array([0.0, 0.3, 0.0]), 0.6, 0.0, scale)


def ood(seed: int, resolution: tuple[int, int], constructs: tuple[str, ...] = ()) -> dict:
    """A held-out scene; `constructs` must be empty (the training mix never reaches this family)."""
    if constructs:
        raise SceneError(
            f"the ood family is held out of training and takes no training constructs, got {list(constructs)}"
        )
    rng = family_rng("ood", seed)
    index = seed % SEEDS_PER_CORPUS
    scene: dict = {}
    scale = exposure(rng)
    layout = LAYOUTS[index % len(LAYOUTS)]
    aim = (_box_layout if layout == "box" else _plinths_layout)(rng, scene, scale)
    scene = new_scene(resolution, aim.eye, aim.target, rng.uniform(35.0, 50.0)) | scene
    lead = OOD_NAMES[(index // len(LAYOUTS)) % len(OOD_NAMES)]
    names = [lead]
    if rng.uniform() < 0.5:
        names.append(OOD_NAMES[int(rng.integers(len(OOD_NAMES)))])
    for name in dict.fromkeys(names):
        OOD_CONSTRUCTS[name](rng, scene, aim)
    return scene
