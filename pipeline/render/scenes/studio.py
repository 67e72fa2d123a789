"""The `studio` family: one to three objects floating in a void, under small lights or a sky.

What the other families lack: most of the frame is environment (coverage 0), often pure black,
and the light comes from small, sometimes visible emitters, so a denoiser learns that black stays
black and that a lit edge next to the void is not noise. Two kinds of lighting:
- void (60 %): a black environment and one or two small area emitters (spheres or panels), so
  everything the camera sees is lit only by them;
- sky (40 %): a sky environment map seen behind the objects, no ground.
Objects are often glass, metal or glossy, sometimes textured; every DIFFUSE_ONLY_EVERY-th seed is
purely diffuse. The camera distance varies so an object may fill the frame or be a small thing in it.
"""

from __future__ import annotations

import numpy as np

from . import materials
from .constructs import Aim, add_constructs
from .geometry import UP, planar
from .staging import OBJECT_KINDS, exposure, family_rng, new_scene, object_material, place_object, rgb, warm_white
from .textures import sky

DIFFUSE_ONLY_EVERY = 4
VOID_CHANCE = 0.6


def _direction(rng: np.random.Generator, min_elevation: float, max_elevation: float) -> np.ndarray:
    azimuth, elevation = rng.uniform(0.0, 2.0 * np.pi), rng.uniform(min_elevation, max_elevation)
    return np.array([np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)])


def _small_light(scene: dict, name: str, rng: np.random.Generator, scale: float, toward: np.ndarray) -> None:
    """A sphere or panel emitter 1-3 m from the objects, on the side of `toward` (a unit vector) give
    or take ~40 degrees. Radiance ~ 1 / size^2 keeps its power fixed whatever its size (a tiny light is
    a bright one), at a level that lights a diffuse object at ~0.1-0.6 like the other families."""
    position = toward + rng.normal(0.0, 0.5, 3)
    position = position / np.linalg.norm(position) * rng.uniform(1.0, 3.0)
    size = rng.uniform(0.03, 0.25)
    radiance = rgb(warm_white(rng) * scale * rng.uniform(1.5, 4.0) / size**2)
    if rng.uniform() < 0.5:
        scene[name] = {
            "type": "sphere",
            "center": position.tolist(),
            "radius": size,
            "emitter": {"type": "area", "radiance": radiance},
        }
    else:
        scene[name] = {
            "type": "rectangle",
            "to_world": planar(position, -position, UP, size, size),
            "emitter": {"type": "area", "radiance": radiance},
        }


def studio(seed: int, resolution: tuple[int, int], constructs: tuple[str, ...] = ()) -> dict:
    rng = family_rng("studio", seed)
    scale = exposure(rng)
    diffuse_only = seed % DIFFUSE_ONLY_EVERY == DIFFUSE_ONLY_EVERY - 1
    fov = rng.uniform(25.0, 45.0)
    distance = rng.uniform(1.0, 4.0)  # objects ~0.2-0.6 m across: from filling the frame to a small thing
    eye = _direction(rng, -0.2, 0.9) * distance
    scene = new_scene(resolution, eye, [0.0, 0.0, 0.0], fov)

    if rng.uniform() < VOID_CHANCE:
        # the key light stands on the camera's side, so the objects' visible faces are lit; a second
        # one may come from anywhere (a rim light, or one the objects hide)
        _small_light(scene, "light_0", rng, scale, eye / distance)
        if rng.uniform() < 0.5:
            _small_light(scene, "light_1", rng, scale, _direction(rng, -0.3, 1.3))
    else:
        scene["environment"] = {"type": "envmap", "bitmap": sky(rng), "scale": scale * rng.uniform(0.5, 1.0)}

    pool = materials.DIFFUSE_KINDS if diffuse_only else materials.ALL_KINDS
    for index in range(int(rng.integers(1, 4))):
        kind = OBJECT_KINDS[int(rng.integers(len(OBJECT_KINDS)))]
        size = rng.uniform(0.1, 0.3)
        x, y, z = rng.uniform(-0.35, 0.35, 3) * (index > 0)
        place_object(scene, f"item_{index}", rng, kind, x, z, y - size, size, object_material(rng, kind, pool))
    return add_constructs(scene, Aim(eye, np.zeros(3), 0.4, None, scale), "studio", seed, constructs)
