"""Named constructs a family composes: lights, occluders, environments, materials, cameras, optics.

A construct adds to (or rewrites part of) a plain scene description, aimed at the family's `Aim`:
where the camera is and looks, how large the region of interest is, whether there is a surface to
stand things on, and the scene's exposure. Breadth grows by adding a construct here; the corpus
mixes them into the training families (`corpus.constructs`, `corpus.construct_chance`), each scene's
choice and each construct's draws on streams of their own, so a scene without constructs is the
family's scene as before.

The held-out family's constructs live in `ood.py` (`OOD_CONSTRUCTS`), never here, and `load_config`
refuses them in `corpus.constructs`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from . import masks
from .geometry import UP, look_at, planar
from .plain import Image, MeshShape
from .staging import family_rng, rgb, warm_white
from .textures import hdr_sky, random_colour

# Irradiance a construct's light puts on the region of interest (before the scene's exposure factor):
# a diffuse surface of albedo 0.5 under it has radiance ~0.5, like the families' own lighting.
TARGET_IRRADIANCE = (2.0, 4.5)


@dataclass(frozen=True)
class Aim:
    """What a construct aims at: the camera position, the centre and radius (m) of the region of interest, the
    height of a surface under it to stand things on (None: things float), and the exposure factor."""

    eye: np.ndarray
    target: np.ndarray
    radius: float
    support: float | None
    scale: float


@dataclass(frozen=True)
class Construct:
    name: str
    kind: str  # light | occluder | environment | material | camera | optics
    add: Callable[[np.random.Generator, dict, Aim], None]
    summary: str
    needs_support: bool = False


def direction_above(rng: np.random.Generator, min_elevation: float = 0.5, max_elevation: float = 1.3) -> np.ndarray:
    azimuth, elevation = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(min_elevation, max_elevation)
    return np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)])


def _aim(position: np.ndarray, target: np.ndarray):
    """look_at with an up vector that is never parallel to the viewing direction."""
    direction = np.asarray(target) - np.asarray(position)
    up = UP if abs(direction[1]) < 0.95 * np.linalg.norm(direction) else np.array([0.0, 0.0, 1.0])
    return look_at(position, target, up)


def irradiance(rng: np.random.Generator, aim: Aim) -> float:
    return rng.uniform(*TARGET_IRRADIANCE) * aim.scale


def _light_position(rng: np.random.Generator, aim: Aim) -> tuple[np.ndarray, float]:
    """A light 1.2-3 m from the target, above it, on the camera's half so the lit side is seen."""
    toward_eye = np.asarray(aim.eye) - aim.target
    direction = direction_above(rng)
    if np.dot(direction[[0, 2]], toward_eye[[0, 2]]) < 0:
        direction[[0, 2]] *= -1.0
    distance = rng.uniform(1.2, 3.0) + aim.radius
    return aim.target + direction * distance, distance


def _textured_light(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """A projector (half the time) or a spot light with a slide: a hard pattern inside the lit region."""
    position, distance = _light_position(rng, aim)
    slide = masks.random_gobo(rng)
    colour = np.asarray(random_colour(rng, saturation=(0.0, 0.4), value=(0.9, 1.0)))
    texture = {"type": "bitmap", "bitmap": Image((0.1 + 0.9 * slide)[..., None] * colour), "filter_type": "bilinear"}
    cover = np.rad2deg(2.0 * np.arctan(rng.uniform(1.2, 2.5) * aim.radius / distance))  # the beam's full angle
    power = irradiance(rng, aim) * distance**2  # irradiance at 1 m (projector) or intensity (spot)
    if rng.uniform() < 0.5:
        scene["projector"] = {
            "type": "projector",
            "to_world": _aim(position, aim.target),
            "irradiance": texture,
            "scale": power,
            "fov": float(min(cover, 60.0)),
        }
    else:
        scene["spot"] = {
            "type": "spot",
            "to_world": _aim(position, aim.target),
            "texture": texture,
            "intensity": rgb([power] * 3),
            "cutoff_angle": float(min(cover, 60.0)),
            "beam_width": float(min(cover, 60.0) * rng.uniform(0.6, 0.95)),
        }


def _occluded_light(rng: np.random.Generator, scene: dict, aim: Aim, opacity: np.ndarray, name: str) -> None:
    """A small light behind a masked card: the card's holes cast hard, high-frequency shadows."""
    position, distance = _light_position(rng, aim)
    power = irradiance(rng, aim) * distance**2
    if rng.uniform() < 0.7:
        scene[f"{name}_light"] = {
            "type": "point",
            "position": position.tolist(),
            "intensity": rgb(warm_white(rng) * power),
        }
    else:
        radius = rng.uniform(0.005, 0.02)
        scene[f"{name}_light"] = {
            "type": "sphere",
            "center": position.tolist(),
            "radius": radius,
            "emitter": {"type": "area", "radiance": rgb(warm_white(rng) * power / (np.pi * radius**2))},
        }
    along = rng.uniform(0.25, 0.6)  # where the card sits between the light and the target
    centre = position + (aim.target - position) * along
    half = rng.uniform(1.3, 2.0) * aim.radius * along
    card_bsdf = {
        "type": "twosided",
        "bsdf": {"type": "diffuse", "reflectance": rgb(random_colour(rng, value=(0.05, 0.4)))},
    }
    scene[name] = {
        "type": "rectangle",
        "to_world": planar(centre, position - centre, direction_above(rng, -1.0, 1.0), half, half),
        "bsdf": {
            "type": "mask",
            "opacity": {"type": "bitmap", "bitmap": Image(1.0 - opacity), "filter_type": "nearest"},
            "bsdf": card_bsdf,
        },
    }


def _grate(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    pattern = (masks.bars, masks.grid, masks.dots)[int(rng.integers(3))](rng)
    _occluded_light(rng, scene, aim, pattern, "grate")


def _foliage(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    _occluded_light(rng, scene, aim, masks.foliage(rng), "foliage")


def _environment_key(scene: dict) -> str | None:
    return next((key for key in ("environment", "sky") if key in scene), None)


def _hdr_environment(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """A procedural HDR sky with a hard sun and sharp panels, replacing the scene's environment (a room
    keeps its window: its sky becomes this one)."""
    key = _environment_key(scene) or "environment"
    scale = scene[key]["scale"] if key in scene and "scale" in scene[key] else aim.scale * rng.uniform(0.7, 1.2)
    scene[key] = {"type": "envmap", "bitmap": hdr_sky(rng), "scale": float(scale)}


def _shapes_with_bsdf(scene: dict) -> list[str]:
    """Keys of the shapes a material construct may rewrite: anything with a BSDF that emits nothing."""
    keys = []
    for key, value in scene.items():
        if isinstance(value, MeshShape) or (isinstance(value, dict) and "bsdf" in value and "emitter" not in value):
            keys.append(key)
    return sorted(keys)


def set_bsdf(scene: dict, key: str, bsdf: dict) -> None:
    """Give the shape under `key` (a dict or a MeshShape) another BSDF."""
    shape = scene[key]
    scene[key] = replace(shape, bsdf=bsdf) if isinstance(shape, MeshShape) else dict(shape, bsdf=bsdf)


def rewrite_bsdf(scene: dict, key: str, wrap: Callable[[dict], dict]) -> None:
    """Apply `wrap` to the shape's BSDF inside any `twosided` (so the wrapper sees the real lobes)."""
    shape = scene[key]
    bsdf = shape.bsdf if isinstance(shape, MeshShape) else shape["bsdf"]
    set_bsdf(scene, key, dict(bsdf, bsdf=wrap(bsdf["bsdf"])) if bsdf.get("type") == "twosided" else wrap(bsdf))


def pick_shapes(rng: np.random.Generator, scene: dict, most: int) -> list[str]:
    keys = [key for key in _shapes_with_bsdf(scene) if not key.startswith(("grate", "foliage"))]
    if not keys:
        return []
    count = min(len(keys), int(rng.integers(1, most + 1)))
    return [keys[i] for i in sorted(rng.choice(len(keys), count, replace=False))]


def bump_shape(rng: np.random.Generator, scene: dict, key: str) -> None:
    """A bump map (half the time) or a normal map of a tiles, ripples or noise height field on one shape."""
    height = masks.random_height(rng)
    if rng.uniform() < 0.5:
        texture = {"type": "bitmap", "bitmap": Image(height), "filter_type": "bilinear"}
        amount = rng.uniform(0.2, 1.0)
        rewrite_bsdf(scene, key, lambda inner: {"type": "bumpmap", "arg": texture, "scale": amount, "bsdf": inner})
    else:
        normals = Image(masks.normal_map(height, rng.uniform(0.01, 0.05)))
        rewrite_bsdf(
            scene,
            key,
            lambda inner: {
                "type": "normalmap",
                "bsdf": inner,
                "normalmap": {"type": "bitmap", "bitmap": normals, "raw": True},
            },
        )


def _bump(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    for key in pick_shapes(rng, scene, 3):
        bump_shape(rng, scene, key)


def textured_roughness(rng: np.random.Generator) -> dict:
    """A rough metal whose roughness varies over the surface (smudges, scratches, tiles): a glossy
    highlight that is sharp in places and blurred in others."""
    low, high = rng.uniform(0.01, 0.08), rng.uniform(0.2, 0.6)
    roughness = low + (high - low) * masks.random_height(rng)
    return {
        "type": "twosided",
        "bsdf": {
            "type": "roughconductor",
            "distribution": "ggx",
            "material": ("Ag", "Al", "Au", "Cu", "Cr")[int(rng.integers(5))],
            "alpha": {"type": "bitmap", "bitmap": Image(roughness), "filter_type": "bilinear"},
        },
    }


def _rough_texture(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    for key in pick_shapes(rng, scene, 2):
        set_bsdf(scene, key, textured_roughness(rng))


def _thin_lens(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """Depth of field: the camera becomes a thin lens focused near the target, some things blurred."""
    sensor = scene["sensor"]
    distance = float(np.linalg.norm(aim.target - np.asarray(aim.eye)))
    scene["sensor"] = dict(
        sensor,
        type="thinlens",
        focus_distance=distance * rng.uniform(0.6, 1.3),
        aperture_radius=distance * rng.uniform(0.015, 0.06),
    )


def base_height(aim: Aim, size: float) -> float:
    return aim.support if aim.support is not None else float(aim.target[1]) - size


def around_target(rng: np.random.Generator, aim: Aim) -> tuple[float, float]:
    angle, reach = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(0.6, 1.3) * aim.radius
    return float(aim.target[0] + reach * np.cos(angle)), float(aim.target[2] + reach * np.sin(angle))


def _mirrors(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """Mirror and glass spheres and a mirror panel near the target: pixels whose paths meet only
    delta surfaces before the environment or a light."""
    for index in range(int(rng.integers(1, 4))):
        size = rng.uniform(0.15, 0.35) * aim.radius
        x, z = around_target(rng, aim)
        if rng.uniform() < 0.6:
            bsdf = {"type": "conductor", "material": "none", "specular_reflectance": rgb([rng.uniform(0.85, 0.97)] * 3)}
        else:
            bsdf = {"type": "dielectric", "int_ior": rng.uniform(1.4, 1.6), "ext_ior": 1.0}
        scene[f"optic_{index}"] = {
            "type": "sphere",
            "center": [x, base_height(aim, size) + size, z],
            "radius": size,
            "bsdf": bsdf,
        }
    if rng.uniform() < 0.5:
        x, z = around_target(rng, aim)
        half = rng.uniform(0.3, 0.6) * aim.radius
        centre = [x, base_height(aim, half) + half, z]
        facing = np.asarray(aim.eye) - centre + rng.normal(0.0, 0.5, 3)
        scene["optic_panel"] = {
            "type": "rectangle",
            "to_world": planar(centre, facing * [1, 0, 1], UP, half, half),
            "bsdf": {"type": "twosided", "bsdf": {"type": "conductor", "material": "none"}},
        }


def _caustic(rng: np.random.Generator, scene: dict, aim: Aim) -> None:
    """A glass ball held over the support under a small, bright light, the light beyond it as seen from
    the camera: the ball focuses it into a caustic on the floor on the camera's side of the ball."""
    size = rng.uniform(0.2, 0.35) * aim.radius
    x, z = around_target(rng, aim)
    centre = np.array([x, base_height(aim, size) + size * rng.uniform(2.0, 3.5), z])
    scene["caustic_glass"] = {
        "type": "sphere",
        "center": centre.tolist(),
        "radius": size,
        "bsdf": {"type": "dielectric", "int_ior": rng.uniform(1.45, 1.7), "ext_ior": 1.0},
    }
    away = centre - np.asarray(aim.eye)
    away = away[[0, 2]] / np.linalg.norm(away[[0, 2]])
    tilt, height = rng.uniform(0.2, 0.6), rng.uniform(0.5, 1.5)
    position = centre + height * np.array([np.sin(tilt) * away[0], np.cos(tilt), np.sin(tilt) * away[1]])
    radius = rng.uniform(0.02, 0.05)  # small enough for a sharp caustic, large enough for a reference to converge
    power = irradiance(rng, aim) * (position[1] - base_height(aim, size)) ** 2
    scene["caustic_light"] = {
        "type": "sphere",
        "center": position.tolist(),
        "radius": radius,
        "emitter": {"type": "area", "radiance": rgb(warm_white(rng) * power / (np.pi * radius**2))},
    }


CONSTRUCTS: dict[str, Construct] = {
    c.name: c
    for c in (
        Construct(
            "projector",
            "light",
            _textured_light,
            "a projector or spot light with a slide (bars, grid, dots, leaves, spokes)",
        ),
        Construct(
            "grate",
            "occluder",
            _grate,
            "a small light behind a card with bars or holes (mask BSDF): hard striped shadows",
        ),
        Construct(
            "foliage", "occluder", _foliage, "a small light behind a leaf-like alpha-masked card: dappled hard shadows"
        ),
        Construct(
            "hdr_sky",
            "environment",
            _hdr_environment,
            "a procedural HDR sky: hard sun, skyline, bright hard-edged panels",
        ),
        Construct("bump", "material", _bump, "bump or normal maps (tiles, ripples, noise) on one to three surfaces"),
        Construct(
            "rough_texture", "material", _rough_texture, "rough metal with textured roughness on one or two surfaces"
        ),
        Construct("thinlens", "camera", _thin_lens, "a thin-lens camera focused near the target: depth of field"),
        Construct(
            "mirrors", "optics", _mirrors, "mirror and glass spheres and a mirror panel that see the environment"
        ),
        Construct(
            "caustic",
            "optics",
            _caustic,
            "a glass ball over the floor under a small bright light: a focused caustic",
            needs_support=True,
        ),
    )
}


def choose_constructs(
    family: str, seed: int, names: tuple[str, ...], chance: float, supported: bool
) -> tuple[str, ...]:
    """The constructs mixed into one scene: with probability `chance`, one or two of `names` (those
    needing a support only where the family has one), drawn from a stream of its own."""
    pool = [name for name in names if supported or not CONSTRUCTS[name].needs_support]
    rng = family_rng(f"{family}/mix", seed)
    if not pool or rng.uniform() >= chance:
        return ()
    count = min(len(pool), int(rng.integers(1, 3)))
    return tuple(pool[i] for i in sorted(rng.choice(len(pool), count, replace=False)))


def add_constructs(scene: dict, aim: Aim, family: str, seed: int, names: tuple[str, ...]) -> dict:
    """Apply the named constructs in order, from one generator keyed by family and seed (so the
    family's own draws, and so a scene without constructs, are unchanged)."""
    rng = family_rng(f"{family}/constructs", seed)
    for name in names:
        CONSTRUCTS[name].add(rng, scene, aim)
    return scene
