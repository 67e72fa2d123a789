"""The `tabletop` family: a few objects on a ground plane under a sky, seen from close by.

Most materials are glossy, metallic or glass (the first object always is), so this family
feeds the specular branch; the environment map is the main light.
"""

from __future__ import annotations

import numpy as np

from . import materials
from .geometry import UP, planar
from .constructs import Aim, add_constructs
from .meshes import ground_quad
from .plain import MeshShape
from .staging import (
    OBJECT_KINDS,
    Layout,
    exposure,
    family_rng,
    new_scene,
    object_material,
    place_object,
    rgb,
    warm_white,
)
from .textures import sky


def tabletop(seed: int, resolution: tuple[int, int], constructs: tuple[str, ...] = ()) -> dict:
    rng = family_rng("tabletop", seed)
    scale = exposure(rng)
    azimuth, elevation, distance = rng.uniform(0, 2 * np.pi), np.deg2rad(rng.uniform(12.0, 35.0)), rng.uniform(1.1, 1.8)
    target = [rng.uniform(-0.1, 0.1), rng.uniform(0.1, 0.25), rng.uniform(-0.1, 0.1)]
    eye = [
        target[0] + distance * np.cos(elevation) * np.sin(azimuth),
        target[1] + distance * np.sin(elevation),
        target[2] + distance * np.cos(elevation) * np.cos(azimuth),
    ]
    scene = new_scene(resolution, eye, target, rng.uniform(32.0, 45.0))

    if rng.uniform() < 0.8:
        scene["environment"] = {"type": "envmap", "bitmap": sky(rng), "scale": scale * rng.uniform(0.7, 1.2)}
    else:
        scene["environment"] = {"type": "constant", "radiance": rgb(warm_white(rng) * scale * rng.uniform(1.0, 1.8))}
    if rng.uniform() < 0.4:
        spot = np.array([rng.uniform(-1.5, 1.5), rng.uniform(1.5, 2.5), rng.uniform(-1.5, 1.5)])
        half = rng.uniform(0.2, 0.4)
        scene["light_panel"] = {
            "type": "rectangle",
            "to_world": planar(spot, -spot, UP, half, half),
            "emitter": {"type": "area", "radiance": rgb(warm_white(rng) * scale * rng.uniform(2.0, 5.0))},
        }

    ground_kind = materials.pick(rng, ("textured", "textured", "roughplastic", "diffuse"))
    scene["ground"] = MeshShape(ground_quad(10.0, rng.uniform(8.0, 20.0)), materials.material(rng, ground_kind))

    layout = Layout()
    for index in range(int(rng.integers(3, 6))):
        kind = materials.pick(rng, OBJECT_KINDS)
        size = rng.uniform(0.1, 0.22)
        spot = layout.free_spot(rng, (-0.45, 0.45), (-0.45, 0.45), size)
        if spot is None:  # the first object always fits, so there is always a specular one
            continue
        pool = materials.SPECULAR_KINDS if index == 0 or rng.uniform() < 0.7 else materials.DIFFUSE_KINDS
        place_object(scene, f"item_{index}", rng, kind, spot[0], spot[1], 0.0, size, object_material(rng, kind, pool))
    return add_constructs(
        scene, Aim(np.asarray(eye), np.asarray(target), 0.5, 0.0, scale), "tabletop", seed, constructs
    )
