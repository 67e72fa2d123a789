"""The `room` family: an indoor room with furniture, objects, a rug and mixed lighting.

Shell (floor, ceiling, walls; one wall may have a window opening onto a sky envmap), 1-2
ceiling light panels, maybe a point light, a table with a vase and small things on it, a cabinet
or shelf against the back wall, objects on the floor, maybe a rug and a wall mirror. The camera
stands inside, 1.6-2.6 m from the table, looking at it. Every DIFFUSE_ONLY_EVERY-th seed is a
purely diffuse room, so a corpus of consecutive seeds exercises the no-specular path at a fixed
rate; every other room has at least one specular object on the table.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import materials
from .geometry import UP, box, planar
from .meshes import heightfield
from .plain import MeshShape
from .constructs import Aim, add_constructs
from .staging import Layout, exposure, family_rng, new_scene, object_material, place_object, rgb, warm_white
from .textures import random_colour, sky

DIFFUSE_ONLY_EVERY = 5


@dataclass
class _Room:
    rng: np.random.Generator
    diffuse_only: bool
    width: float
    depth: float
    height: float
    scale: float
    scene: dict = field(default_factory=dict)
    layout: Layout = field(default_factory=Layout)

    def kind(self, diffuse: str, other: str, chance_of_other: float) -> str:
        """`other` with the given chance, unless the room must stay diffuse."""
        return diffuse if self.diffuse_only or self.rng.uniform() >= chance_of_other else other

    @property
    def material_kinds(self) -> tuple[str, ...]:
        return materials.DIFFUSE_KINDS if self.diffuse_only else materials.ALL_KINDS


def _wall_pieces(center, normal, length: float, height: float, hole=None) -> list[dict]:
    """A wall as rectangles facing `normal`; `hole` = (s0, s1, t0, t1) cuts a window opening.

    s runs along the wall from -length/2 to length/2, t from the floor (0) to `height`.
    """
    along = np.cross(UP, np.asarray(normal, dtype=np.float64))
    spans = [(-length / 2, length / 2, 0.0, height)]
    if hole is not None:
        s0, s1, t0, t1 = hole
        spans = [
            (-length / 2, length / 2, 0.0, t0),
            (-length / 2, length / 2, t1, height),
            (-length / 2, s0, t0, t1),
            (s1, length / 2, t0, t1),
        ]
    return [
        {
            "type": "rectangle",
            "to_world": planar(
                np.asarray(center) + along * (a + b) / 2 + UP * (c + d) / 2, normal, UP, (b - a) / 2, (d - c) / 2
            ),
        }
        for a, b, c, d in spans
    ]


def _shell(room: _Room) -> None:
    rng, w, d, h, scene = room.rng, room.width, room.depth, room.height, room.scene
    scene["floor"] = {
        "type": "rectangle",
        "to_world": planar([0, 0, 0], UP, [0, 0, -1], w / 2, d / 2),
        "bsdf": materials.material(rng, room.kind("textured", "roughplastic", 0.4)),
    }
    scene["ceiling"] = {
        "type": "rectangle",
        "to_world": planar([0, h, 0], -UP, [0, 0, 1], w / 2, d / 2),
        "bsdf": {"type": "diffuse", "reflectance": rgb([rng.uniform(0.7, 0.85)] * 3)},
    }
    walls = {  # name: (centre at floor level, inward normal, length)
        "back": ([0, 0, -d / 2], [0, 0, 1], w),
        "front": ([0, 0, d / 2], [0, 0, -1], w),
        "left": ([-w / 2, 0, 0], [1, 0, 0], d),
        "right": ([w / 2, 0, 0], [-1, 0, 0], d),
    }
    window_wall = ("back", "left", "right", None)[int(rng.integers(4))]
    wall_colour = random_colour(rng, saturation=(0.05, 0.3), value=(0.55, 0.8))
    for name in ("back", "front", "left", "right"):
        center, normal, length = walls[name]
        hole = None
        if name == window_wall:
            half, sill = rng.uniform(0.5, 0.9), rng.uniform(0.8, 1.0)
            middle = rng.uniform(-length / 2 + half + 0.4, length / 2 - half - 0.4)
            hole = (middle - half, middle + half, sill, min(sill + rng.uniform(0.8, 1.3), h - 0.2))
        textured = not room.diffuse_only and rng.uniform() < 0.25
        bsdf = materials.material(rng, "textured") if textured else {"type": "diffuse", "reflectance": rgb(wall_colour)}
        for index, piece in enumerate(_wall_pieces(center, normal, length, h, hole)):
            scene[f"wall_{name}_{index}"] = dict(piece, bsdf=bsdf)
    if window_wall is not None:
        scene["sky"] = {"type": "envmap", "bitmap": sky(rng), "scale": room.scale * rng.uniform(4.0, 8.0)}


def _lights(room: _Room) -> None:
    """Ceiling panels of fixed power whatever their size, and sometimes a point light."""
    rng, w, d, h = room.rng, room.width, room.depth, room.height
    for index in range(int(rng.integers(1, 3))):
        half_x, half_z = rng.uniform(0.2, 0.45), rng.uniform(0.2, 0.45)
        spot = [rng.uniform(-0.3, 0.3) * w, h - 0.005, rng.uniform(-0.3, 0.3) * d]
        radiance = warm_white(rng) * room.scale * rng.uniform(3.0, 5.0) / (half_x * half_z)
        room.scene[f"light_panel_{index}"] = {
            "type": "rectangle",
            "to_world": planar(spot, -UP, [0, 0, 1], half_x, half_z),
            "emitter": {"type": "area", "radiance": rgb(radiance)},
        }
    if rng.uniform() < 0.4:
        room.scene["light_point"] = {
            "type": "point",
            "intensity": rgb(warm_white(rng) * room.scale * rng.uniform(3.0, 8.0)),
            "position": [rng.uniform(-0.3, 0.3) * w, h - rng.uniform(0.4, 0.8), rng.uniform(-0.3, 0.3) * d],
        }


def _table(room: _Room, x: float, z: float) -> tuple[float, float]:
    """A table at (x, z) with a vase and one or two small things on it; returns (yaw, height)."""
    rng, scene = room.rng, room.scene
    half = [rng.uniform(0.4, 0.7), 0.025, rng.uniform(0.3, 0.5)]
    top, yaw = rng.uniform(0.7, 0.8), rng.uniform(-30.0, 30.0)
    room.layout.claim(x, z, float(np.hypot(half[0], half[2])))
    scene["table_top"] = {
        "type": "cube",
        "to_world": box([x, top - half[1], z], half, yaw),
        "bsdf": materials.material(rng, room.kind("textured", "roughplastic", 0.5)),
    }
    leg_bsdf = materials.material(rng, room.kind("diffuse", "roughconductor", 0.5))
    cos, sin = np.cos(np.deg2rad(yaw)), np.sin(np.deg2rad(yaw))

    def on_table(local_x: float, local_z: float) -> tuple[float, float]:
        return x + cos * local_x + sin * local_z, z - sin * local_x + cos * local_z

    for index, (sx, sz) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
        leg_x, leg_z = on_table(sx * (half[0] - 0.05), sz * (half[2] - 0.05))
        leg_half = (top - 0.05) / 2
        scene[f"table_leg_{index}"] = {
            "type": "cube",
            "to_world": box([leg_x, leg_half, leg_z], [0.03, leg_half, 0.03], yaw),
            "bsdf": leg_bsdf,
        }

    kinds = ["vase"] + [
        materials.pick(rng, ("sphere", "box", "cylinder", "bumpy")) for _ in range(int(rng.integers(1, 3)))
    ]
    for index, kind in enumerate(kinds):
        size = rng.uniform(0.06, 0.12)
        item_x, item_z = on_table(rng.uniform(-1, 1) * (half[0] - size), rng.uniform(-1, 1) * (half[2] - size))
        pool = materials.SPECULAR_KINDS if index == 0 and not room.diffuse_only else room.material_kinds
        place_object(
            scene, f"table_item_{index}", rng, kind, item_x, item_z, top, size, object_material(rng, kind, pool)
        )
    return yaw, top


def _storage(room: _Room) -> None:
    """A closed cabinet or an open shelf (three boards, two sides) against the back wall."""
    rng, scene = room.rng, room.scene
    bsdf = materials.material(
        rng,
        materials.pick(rng, ("diffuse", "textured") if room.diffuse_only else ("diffuse", "textured", "roughplastic")),
    )
    x = rng.uniform(-0.3, 0.3) * room.width
    half = [rng.uniform(0.35, 0.7), rng.uniform(0.3, 0.9), rng.uniform(0.2, 0.3)]
    z = -room.depth / 2 + half[2] + 0.01
    room.layout.claim(x, z, float(np.hypot(half[0], half[2])))
    if rng.uniform() < 0.5:
        scene["cabinet"] = {"type": "cube", "to_world": box([x, half[1], z], half), "bsdf": bsdf}
        return
    for level in range(3):
        y = 0.02 + level * (half[1] - 0.02)
        scene[f"shelf_board_{level}"] = {
            "type": "cube",
            "to_world": box([x, y, z], [half[0], 0.02, half[2]]),
            "bsdf": bsdf,
        }
    for side in (-1, 1):
        scene[f"shelf_side_{side + 1}"] = {
            "type": "cube",
            "to_world": box([x + side * (half[0] + 0.02), half[1], z], [0.02, half[1], half[2]]),
            "bsdf": bsdf,
        }


def room(seed: int, resolution: tuple[int, int], constructs: tuple[str, ...] = ()) -> dict:
    rng = family_rng("room", seed)
    width, depth, height = rng.uniform(4.0, 6.5), rng.uniform(4.0, 6.5), rng.uniform(2.5, 3.2)
    room = _Room(rng, seed % DIFFUSE_ONLY_EVERY == 0, width, depth, height, exposure(rng))
    target = [rng.uniform(-0.2, 0.2) * width, rng.uniform(0.6, 0.9), rng.uniform(-0.3, 0.0) * depth]
    eye = [
        target[0] + rng.uniform(-0.8, 0.8),
        rng.uniform(1.2, 1.7),
        min(target[2] + rng.uniform(1.6, 2.6), depth / 2 - 0.3),
    ]
    room.scene = new_scene(resolution, eye, target, rng.uniform(55.0, 75.0))
    _shell(room)
    _lights(room)
    table_yaw, table_height = _table(room, target[0], target[2])
    _storage(room)

    for index in range(int(rng.integers(1, 4))):
        kind = materials.pick(rng, ("sphere", "cylinder", "bumpy", "box"))
        size = rng.uniform(0.15, 0.3)
        spot = room.layout.free_spot(
            rng, (-width / 2 + 0.5, width / 2 - 0.5), (-depth / 2 + 0.5, depth / 2 - 1.5), size
        )
        if spot is not None:
            place_object(
                room.scene,
                f"floor_item_{index}",
                rng,
                kind,
                spot[0],
                spot[1],
                0.0,
                size,
                object_material(rng, kind, room.material_kinds),
            )
    if rng.uniform() < 0.5:
        rug = heightfield(
            rng, (rng.uniform(1.5, 2.5), rng.uniform(1.2, 2.0)), 0.008, [target[0], 0.01, target[2]], table_yaw
        )
        room.scene["rug"] = MeshShape(rug, materials.material(rng, "textured"))
    if not room.diffuse_only and rng.uniform() < 0.3:
        side, half = (1.0 if rng.uniform() < 0.5 else -1.0), rng.uniform(0.3, 0.6)
        center = [-side * (width / 2 - 0.01), rng.uniform(1.1, 1.5), rng.uniform(-0.3, 0.1) * depth]
        room.scene["wall_mirror"] = {
            "type": "rectangle",
            "to_world": planar(center, [side, 0, 0], UP, half, half * rng.uniform(0.8, 1.4)),
            "bsdf": materials.material(rng, "mirror"),
        }
    aim = Aim(np.asarray(eye), np.array([target[0], table_height, target[2]]), 0.6, table_height, room.scale)
    return add_constructs(room.scene, aim, "room", seed, constructs)
