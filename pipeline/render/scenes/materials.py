"""Seeded BSDF dicts (plain descriptions) for the procedural families.

Opaque materials are wrapped in `twosided` so open meshes and thin sheets never show a black
back face; glass stays a bare `dielectric` (it is two-sided by nature and must not be wrapped).
"""

from __future__ import annotations

import numpy as np

from .textures import random_colour, random_pattern

DIFFUSE_KINDS = ("diffuse", "textured")
SPECULAR_KINDS = ("roughplastic", "roughconductor", "conductor", "glass", "mirror")
ALL_KINDS = DIFFUSE_KINDS + SPECULAR_KINDS
METALS = ("Ag", "Al", "Au", "Cr", "Cu", "Ir")


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(c) for c in value]}


def _albedo(rng: np.random.Generator, textured: bool) -> dict:
    if textured:
        return {"type": "bitmap", "bitmap": random_pattern(rng), "filter_type": "bilinear"}
    return _rgb(random_colour(rng))


def _two_sided(bsdf: dict) -> dict:
    return {"type": "twosided", "bsdf": bsdf}


def material(rng: np.random.Generator, kind: str) -> dict:
    """One BSDF of the given kind (see ALL_KINDS) with seeded parameters."""
    if kind == "diffuse":
        return _two_sided({"type": "diffuse", "reflectance": _albedo(rng, textured=False)})
    if kind == "textured":
        return _two_sided({"type": "diffuse", "reflectance": _albedo(rng, textured=True)})
    if kind == "roughplastic":
        return _two_sided(
            {
                "type": "roughplastic",
                "distribution": "ggx",
                "alpha": rng.uniform(0.05, 0.3),
                "int_ior": rng.uniform(1.4, 1.6),
                "diffuse_reflectance": _albedo(rng, textured=rng.uniform() < 0.4),
            }
        )
    if kind == "roughconductor":
        return _two_sided(
            {
                "type": "roughconductor",
                "distribution": "ggx",
                "material": METALS[int(rng.integers(len(METALS)))],
                "alpha": rng.uniform(0.05, 0.35),
            }
        )
    if kind == "conductor":
        return _two_sided({"type": "conductor", "material": METALS[int(rng.integers(len(METALS)))]})
    if kind == "mirror":
        return _two_sided(
            {"type": "conductor", "material": "none", "specular_reflectance": _rgb([rng.uniform(0.85, 0.95)] * 3)}
        )
    if kind == "glass":
        tint = 1.0 - 0.15 * np.asarray(random_colour(rng, saturation=(0.0, 0.6), value=(0.5, 1.0)))
        return {
            "type": "dielectric",
            "int_ior": rng.uniform(1.4, 1.6),
            "ext_ior": 1.0,
            "specular_transmittance": _rgb(tint),
        }
    raise KeyError(f"unknown material kind {kind!r}; known: {', '.join(ALL_KINDS)}")


def pick(rng: np.random.Generator, kinds: tuple[str, ...]) -> str:
    return kinds[int(rng.integers(len(kinds)))]
