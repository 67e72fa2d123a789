"""The `preview` family: one object on a textured floor under an environment map, seen from close by.

The material-preview setup: most of the frame is a flat textured floor lit by a (usually HDR,
sharp-sunned) environment, where a denoiser must keep the pattern clean at 4 spp, plus one object
whose material is the subject: any of the families' materials, textured roughness, or a bump or
normal map. The object is a sphere, a bumpy sphere, a vase, a box, or a ball on a pedestal.
"""

from __future__ import annotations

import numpy as np

from . import materials
from .constructs import Aim, add_constructs, bump_shape, set_bsdf, textured_roughness
from .meshes import ground_quad
from .plain import MeshShape
from .staging import exposure, family_rng, new_scene, object_material, place_object, rgb
from .textures import checker, hdr_sky, sky

SHAPES = ("sphere", "bumpy", "vase", "box", "pedestal")


def _subject(rng: np.random.Generator, scene: dict, shape: str, size: float) -> None:
    if shape == "pedestal":  # a ball on a short column, like a material-preview "shader ball"
        column = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": rgb([rng.uniform(0.2, 0.6)] * 3)}}
        place_object(scene, "pedestal", rng, "cylinder", 0.0, 0.0, 0.0, 0.5 * size, column)
        top = scene["pedestal"]["p1"][1]
        scene["subject"] = {"type": "sphere", "center": [0.0, top + size, 0.0], "radius": size}
    else:
        place_object(scene, "subject", rng, shape, 0.0, 0.0, 0.0, size, {})
    roll = rng.uniform()
    if roll < 0.25:
        bsdf = textured_roughness(rng)
    else:
        bsdf = object_material(rng, "sphere" if shape == "pedestal" else shape, materials.ALL_KINDS)
    set_bsdf(scene, "subject", bsdf)
    if roll > 0.7:  # a bump or normal map on the subject
        bump_shape(rng, scene, "subject")


def preview(seed: int, resolution: tuple[int, int], constructs: tuple[str, ...] = ()) -> dict:
    rng = family_rng("preview", seed)
    scale = exposure(rng)
    size = rng.uniform(0.12, 0.25)
    azimuth, elevation, distance = (
        rng.uniform(0, 2 * np.pi),
        np.deg2rad(rng.uniform(5.0, 35.0)),
        rng.uniform(4.0, 9.0) * size,
    )
    target = np.array([0.0, size, 0.0])
    eye = target + distance * np.array(
        [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
    )
    scene = new_scene(resolution, eye, target, rng.uniform(30.0, 50.0))
    bitmap = hdr_sky(rng) if rng.uniform() < 0.75 else sky(rng)
    scene["environment"] = {"type": "envmap", "bitmap": bitmap, "scale": scale * rng.uniform(0.7, 1.2)}
    floor = (
        materials.material(rng, "textured")
        if rng.uniform() < 0.4
        else {
            "type": "twosided",
            "bsdf": {
                "type": "diffuse",
                "reflectance": {"type": "bitmap", "bitmap": checker(rng), "filter_type": "bilinear"},
            },
        }
    )
    scene["floor"] = MeshShape(ground_quad(10.0, rng.uniform(10.0, 40.0)), floor)
    _subject(rng, scene, SHAPES[int(rng.integers(len(SHAPES)))], size)
    aim = Aim(eye, target, 2.0 * size, 0.0, scale)
    return add_constructs(scene, aim, "preview", seed, constructs)
