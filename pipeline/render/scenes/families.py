"""The registry of procedural families and the corpus of specs drawn from them.

A family turns (seed, resolution) into a plain description (see `plain.py`). Radiances are
tuned so a 16-spp `path` render has a mean luminance around 0.1-0.6 before the per-scene
exposure factor (2^-2..2^2) is applied.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from .room import room
from .spec import SceneError, SceneSpec
from .studio import studio
from .tabletop import tabletop

SEEDS_PER_CORPUS = 1_000_000  # scene seeds of corpus seed s are s * SEEDS_PER_CORPUS + k


@dataclass(frozen=True)
class Family:
    name: str
    build: Callable[[int, tuple[int, int]], dict]
    summary: str


FAMILIES: dict[str, Family] = {
    "room": Family("room", room, "indoor room, furniture, textured/glossy/glass materials, area/point/sky light"),
    "tabletop": Family("tabletop", tabletop, "objects on a ground plane under a sky, close view, mostly specular"),
    "studio": Family("studio", studio, "objects floating in a black void under small emitters, or before a sky"),
}


def procedural_corpus(families: list[str], n_scenes: int, seed: int, resolution: tuple[int, int]) -> list[SceneSpec]:
    """`n_scenes` specs cycling through `families`; the k-th scene of a family gets seed
    seed * SEEDS_PER_CORPUS + k, so corpora with different seeds never share a scene."""
    unknown = [name for name in families if name not in FAMILIES]
    if unknown or not families:
        raise SceneError(f"unknown procedural families {unknown or families!r}; known: {', '.join(sorted(FAMILIES))}")
    if n_scenes < 0 or seed < 0:
        raise SceneError(f"n_scenes and seed must be non-negative, got n_scenes={n_scenes}, seed={seed}")
    if n_scenes > len(families) * SEEDS_PER_CORPUS:
        raise SceneError(f"n_scenes={n_scenes} exceeds {SEEDS_PER_CORPUS} scenes per family")
    specs = []
    for index in range(n_scenes):
        family = families[index % len(families)]
        scene_seed = seed * SEEDS_PER_CORPUS + index // len(families)
        specs.append(SceneSpec(f"{family}-{scene_seed:04d}", family, scene_seed, tuple(resolution)))
    return specs
