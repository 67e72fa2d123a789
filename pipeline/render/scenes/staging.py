"""Building blocks shared by the procedural families: the generator, camera, colours,
object placement and the objects themselves.

Every random choice comes from one explicit PCG64 generator keyed by the family name and the
seed, so the same seed gives the same scene on any machine.
"""

from __future__ import annotations

import zlib

import numpy as np

from . import materials
from .geometry import UP, box, look_at, planar
from .meshes import bumpy_sphere, heightfield, lathe
from .plain import MeshShape

OBJECT_KINDS = ("sphere", "bumpy", "vase", "box", "cylinder", "wavy")
OPAQUE_KINDS = ("box", "cylinder", "wavy")  # open or thin shapes: never glass


def family_rng(family: str, seed: int) -> np.random.Generator:
    """The one generator a scene draws from; keyed by family so families never share streams."""
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence([zlib.crc32(family.encode()), int(seed)])))


def exposure(rng: np.random.Generator) -> float:
    """A per-scene factor on every emitter, 2^-2..2^2, so the corpus spans a range of brightness."""
    return 2.0 ** rng.uniform(-2.0, 2.0)


def new_scene(resolution: tuple[int, int], eye, target, fov: float) -> dict:
    """A scene dict with a perspective camera on an hdrfilm with a box filter (and a default
    `path` integrator; the render stage brings its own)."""
    width, height = resolution
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8},
        "sensor": {
            "type": "perspective",
            "fov": float(fov),
            "fov_axis": "x",
            "near_clip": 0.01,
            "far_clip": 1000.0,
            "to_world": look_at(eye, target),
            "film": {
                "type": "hdrfilm",
                "width": width,
                "height": height,
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
            "sampler": {"type": "independent", "sample_count": 4},
        },
    }


def rgb(value) -> dict:
    return {"type": "rgb", "value": [float(c) for c in value]}


def warm_white(rng: np.random.Generator) -> np.ndarray:
    return np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.65, 0.95)])


class Layout:
    """Rejection sampling of non-overlapping circular footprints on the floor plane."""

    def __init__(self) -> None:
        self.footprints: list[tuple[float, float, float]] = []

    def claim(self, x: float, z: float, radius: float) -> None:
        self.footprints.append((x, z, radius))

    def free_spot(self, rng: np.random.Generator, x_range, z_range, radius: float, tries: int = 40):
        """A claimed (x, z) clear of every footprint, or None when none was found."""
        for _ in range(tries):
            x, z = rng.uniform(*x_range), rng.uniform(*z_range)
            if all((x - fx) ** 2 + (z - fz) ** 2 > (radius + fr) ** 2 for fx, fz, fr in self.footprints):
                self.claim(x, z, radius)
                return x, z
        return None


def _vase_radii(rng: np.random.Generator, size: float, rings: int = 20) -> np.ndarray:
    s = np.linspace(0.0, 1.0, rings)
    bulge = 0.35 * np.sin(np.pi * (rng.uniform(0.8, 1.8) * s + rng.uniform(-0.3, 0.3)))
    return size * np.clip(0.45 + bulge + rng.uniform(-0.3, 0.3) * s, 0.15, 1.0)


def object_material(rng: np.random.Generator, kind: str, material_kinds: tuple[str, ...]) -> dict:
    """A material from `material_kinds` that suits the object (no glass on open shapes)."""
    if kind in OPAQUE_KINDS:
        material_kinds = tuple(k for k in material_kinds if k != "glass") or materials.DIFFUSE_KINDS
    return materials.material(rng, materials.pick(rng, material_kinds))


def place_object(
    scene: dict,
    name: str,
    rng: np.random.Generator,
    kind: str,
    x: float,
    z: float,
    base: float,
    size: float,
    bsdf: dict,
) -> None:
    """Add one object standing on height `base` at (x, z), footprint radius ~`size`."""
    if kind == "sphere":
        scene[name] = {"type": "sphere", "center": [x, base + size, z], "radius": size, "bsdf": bsdf}
    elif kind == "bumpy":
        scene[name] = MeshShape(bumpy_sphere(rng, 0.9 * size, [x, base + size, z]), bsdf)
    elif kind == "vase":
        scene[name] = MeshShape(lathe(_vase_radii(rng, size), size * rng.uniform(1.5, 3.0), [x, base, z]), bsdf)
    elif kind == "box":
        half = size * rng.uniform(0.5, 0.7, 3)
        scene[name] = {
            "type": "cube",
            "to_world": box([x, base + half[1], z], half, rng.uniform(0.0, 90.0)),
            "bsdf": bsdf,
        }
    elif kind == "cylinder":
        top = base + size * rng.uniform(1.0, 3.0)
        scene[name] = {"type": "cylinder", "p0": [x, base, z], "p1": [x, top, z], "radius": size, "bsdf": bsdf}
        scene[f"{name}_cap"] = {
            "type": "disk",
            "to_world": planar([x, top, z], UP, [0.0, 0.0, -1.0], size, size),
            "bsdf": bsdf,
        }
    elif kind == "wavy":
        sheet = heightfield(
            rng, (2 * size, 2 * size), 0.15 * size, [x, base + 0.15 * size, z], rng.uniform(0.0, 90.0), 20
        )
        scene[name] = MeshShape(sheet, bsdf)
    else:
        raise KeyError(f"unknown object kind {kind!r}; known: {', '.join(OBJECT_KINDS)}")
