"""The registry of procedural families and the corpus of specs drawn from them.

A family turns (seed, resolution, constructs) into a plain description (see `plain.py`); the
constructs (`constructs.py`) are mixed in on top of the family's own draws. Radiances are tuned so
a 16-spp `path` render has a mean luminance around 0.1-0.6 before the per-scene exposure factor
(2^-2..2^2) is applied.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from .constructs import CONSTRUCTS, choose_constructs
from .ood import ood
from .preview import preview
from .room import room
from .spec import SEEDS_PER_CORPUS, SceneError, SceneSpec
from .studio import studio
from .tabletop import tabletop


@dataclass(frozen=True)
class Family:
    name: str
    build: Callable[[int, tuple[int, int], tuple[str, ...]], dict]
    summary: str
    has_support: bool  # a surface near the target that constructs may stand things on


FAMILIES: dict[str, Family] = {
    "room": Family("room", room, "indoor room, furniture, textured/glossy/glass materials, area/point/sky light", True),
    "tabletop": Family(
        "tabletop", tabletop, "objects on a ground plane under a sky, close view, mostly specular", True
    ),
    "studio": Family("studio", studio, "objects floating in a black void under small emitters, or before a sky", False),
    "preview": Family(
        "preview", preview, "one object on a textured floor under an (HDR) environment map, close view", True
    ),
    "ood": Family(
        "ood", ood, "held out of training: a closed box or plinths with constructs no training family has", True
    ),
}


def scene_id(family: str, seed: int, constructs: tuple[str, ...] = ()) -> str:
    """`room-1000003`, or `room-1000003+projector+thinlens` when constructs are mixed in."""
    return f"{family}-{seed:04d}" + "".join(f"+{name}" for name in constructs)


def procedural_corpus(
    families: list[str],
    n_scenes: int,
    seed: int,
    resolution: tuple[int, int],
    constructs: tuple[str, ...] = (),
    construct_chance: float = 0.0,
) -> list[SceneSpec]:
    """`n_scenes` specs cycling through `families`; the k-th scene of a family gets seed
    seed * SEEDS_PER_CORPUS + k, so corpora with different seeds never share a scene. Each scene gets
    one or two of `constructs` with probability `construct_chance` (a draw of its own per scene)."""
    unknown = [name for name in families if name not in FAMILIES]
    if unknown or not families:
        raise SceneError(f"unknown procedural families {unknown or families!r}; known: {', '.join(sorted(FAMILIES))}")
    unknown = [name for name in constructs if name not in CONSTRUCTS]
    if unknown:
        raise SceneError(f"unknown constructs {unknown!r}; known: {', '.join(sorted(CONSTRUCTS))}")
    if n_scenes < 0 or seed < 0:
        raise SceneError(f"n_scenes and seed must be non-negative, got n_scenes={n_scenes}, seed={seed}")
    if n_scenes > len(families) * SEEDS_PER_CORPUS:
        raise SceneError(f"n_scenes={n_scenes} exceeds {SEEDS_PER_CORPUS} scenes per family")
    specs = []
    for index in range(n_scenes):
        family = families[index % len(families)]
        scene_seed = seed * SEEDS_PER_CORPUS + index // len(families)
        mixed = choose_constructs(family, scene_seed, tuple(constructs), construct_chance, FAMILIES[family].has_support)
        specs.append(
            SceneSpec(scene_id(family, scene_seed, mixed), family, scene_seed, tuple(resolution), constructs=mixed)
        )
    return specs
