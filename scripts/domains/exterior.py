"""`exterior`: one small house on a lawn (the set of a seed: brick walls, a tiled gable roof, windows, a
door, a paved path, a fence, trees and a car) under Mitsuba's sun and sky at four times of day, seen
from eye level and from a drone around it."""

from __future__ import annotations

import colorsys
import math
from pathlib import Path

import numpy as np

from . import assets
from .scenexml import Scene, bitmap, box, bsdf, frame, rotation_y, sun_direction

TIMES = (
    (35.0, 55.0, 2.5),
    (120.0, 30.0, 3.0),
    (200.0, 14.0, 4.0),
    (300.0, 8.0, 5.0),
)  # sun azimuth, elevation, turbidity
SKY = 2.0  # sunsky scale


def _colour(rng: np.random.Generator, saturation, value) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*saturation), rng.uniform(*value)))


class House:
    def __init__(self, seed: int, out_dir: Path):
        rng = np.random.default_rng([seed, 7201])
        self.seed = seed
        self.width, self.depth, self.wall = rng.uniform(7.0, 9.0), rng.uniform(5.5, 7.0), rng.uniform(2.8, 3.2)
        self.pitch = rng.uniform(0.55, 0.8)  # roof rise over half the depth

        def name(part):
            return out_dir / f"exterior-{seed}-{part}"

        brick = np.array([0.5, 0.2, 0.12]) * rng.uniform(0.7, 1.2)
        self.tex = {
            "brick": assets.write_texture(name("brick.exr"), assets.bricks(rng, brick, rows=8)),
            "roof": assets.write_texture(
                name("roof.exr"), assets.roof_tiles(rng, _colour(rng, (0.3, 0.7), (0.15, 0.4)))
            ),
            "grass": assets.write_texture(name("grass.exr"), assets.grass(rng)),
            "paving": assets.write_texture(name("paving.exr"), assets.tiles(rng, np.array([0.45, 0.43, 0.4]), 4)),
            "leaves": assets.write_texture(name("leaves.exr"), assets.leaves(rng)),
            "door": assets.write_texture(name("door.exr"), assets.wood_planks(rng, np.array([0.35, 0.18, 0.08]), 5)),
        }
        rise = self.pitch * self.depth / 2
        self.gable = assets.write_obj(
            name("gable.obj"), assets.prism([[-self.depth / 2, 0], [self.depth / 2, 0], [0, rise]], 0.3)
        )
        self.car_colour = _colour(rng, (0.6, 1.0), (0.2, 0.6))
        self.trees = [
            (rng.uniform(-14, 14), rng.uniform(-12, -6) if k % 2 else rng.uniform(6, 12), rng.uniform(2.5, 4.5))
            for k in range(5)
        ]

    def frame(self, index: int) -> Scene:
        azimuth, elevation, turbidity = TIMES[index % len(TIMES)]
        rng = np.random.default_rng([self.seed, 7202, index])
        s = Scene(
            f" exterior set {self.seed}, frame {index} (sun at {elevation:g} degrees), written by "
            "scripts/make_domain_scenes.py "
        )
        s.sunsky(sun_direction(azimuth, elevation), turbidity=turbidity, sun_scale=SKY, sky_scale=SKY, albedo=0.2)
        self._ground(s)
        self._house(s)
        self._garden(s)
        self._camera(s, rng)
        return s

    def _ground(self, s: Scene) -> None:
        s.bsdf("grass", bsdf("diffuse", texture=bitmap("", self.tex["grass"], (250, 250))))
        s.shape("rectangle", "grass", frame((0, 0, 0), (0, 1, 0), (0, 0, -1), 500, 500))
        s.bsdf("paving", bsdf("roughplastic", texture=bitmap("", self.tex["paving"], (1, 6)), alpha=0.4))
        s.shape("rectangle", "paving", frame((0, 0.01, self.depth / 2 + 4.5), (0, 1, 0), (0, 0, -1), 0.8, 4.5))
        s.shape(
            "rectangle",
            "paving",
            frame((-self.width / 2 - 2.5, 0.01, self.depth / 2 + 3), (0, 1, 0), (0, 0, -1), 1.6, 3),
        )

    def _house(self, s: Scene) -> None:
        w, d, h = self.width, self.depth, self.wall
        s.bsdf("brick", bsdf("diffuse", texture=bitmap("", self.tex["brick"], (w / 2.0, h / 1.0))))
        s.bsdf("brick-side", bsdf("diffuse", texture=bitmap("", self.tex["brick"], (d / 2.0, h / 1.0))))
        s.bsdf("glass", bsdf("plastic", (0.01, 0.012, 0.015), int_ior=1.5))
        s.bsdf("trim", bsdf("roughplastic", (0.8, 0.8, 0.78), alpha=0.25))
        s.bsdf("door", bsdf("roughplastic", texture=bitmap("", self.tex["door"], (1, 1)), alpha=0.2))
        for z, normal in ((d / 2, (0, 0, 1)), (-d / 2, (0, 0, -1))):
            s.shape("rectangle", "brick", frame((0, h / 2, z), normal, (0, 1, 0), w / 2, h / 2))
        for x, normal in ((w / 2, (1, 0, 0)), (-w / 2, (-1, 0, 0))):
            s.shape("rectangle", "brick-side", frame((x, h / 2, 0), normal, (0, 1, 0), d / 2, h / 2))
        for x in (-w / 3, w / 3):  # front windows, a back window and one per side
            self._window(s, (x, 1.6, d / 2), (0, 0, 1))
            self._window(s, (x, 1.6, -d / 2), (0, 0, -1))
        for x, normal in ((w / 2, (1, 0, 0)), (-w / 2, (-1, 0, 0))):
            self._window(s, (x, 1.6, 0), normal)
        s.shape("rectangle", "door", frame((0, 1.05, d / 2 + 0.02), (0, 0, 1), (0, 1, 0), 0.5, 1.05))
        s.shape("cube", "trim", box((0, 2.15, d / 2 + 0.05), (0.62, 0.06, 0.05)))
        s.shape("cube", "trim", box((0, 0.08, d / 2 + 0.4), (0.8, 0.08, 0.4)))  # the step
        # gable roof: two tiled planes overhanging the walls, gable ends of brick
        rise, over = self.pitch * d / 2, 0.4
        slope = math.hypot(d / 2 + over, rise * (1 + over / (d / 2)))
        s.bsdf("roof", bsdf("roughplastic", texture=bitmap("", self.tex["roof"], (w / 1.5, slope / 1.0)), alpha=0.3))
        for side in (-1, 1):
            normal = np.array([0, d / 2, side * rise])
            up = np.array([0, rise, -side * d / 2])
            centre = (0, h + rise / 2, side * d / 4)
            s.shape("rectangle", "roof", frame(centre, normal, up, w / 2 + over, slope / 2))
            s.shape(
                "obj",
                "brick-side",
                box((side * (w / 2 - 0.15), h, 0), (1, 1, 1)) @ rotation_y(math.pi / 2),
                filename=self.gable,
            )
        s.shape("cube", "brick", box((w / 4, h + rise * 0.8, -d / 6), (0.35, rise * 0.6, 0.35)))  # chimney

    def _window(self, s: Scene, centre, normal) -> None:
        normal = np.asarray(normal, float)
        c = np.asarray(centre, float) + normal * 0.02
        s.shape("rectangle", "glass", frame(c, normal, (0, 1, 0), 0.55, 0.6))
        side = np.cross((0, 1, 0), normal)
        for offset, half in (
            (side * 0.6, (0.05, 0.65)),
            (-side * 0.6, (0.05, 0.65)),
            ((0, 0.65, 0), (0.65, 0.05)),
            ((0, -0.65, 0), (0.7, 0.06)),
            ((0, 0, 0), (0.03, 0.6)),
        ):
            hx = abs(side[0]) * half[0] + abs(normal[0]) * 0.04
            hz = abs(side[2]) * half[0] + abs(normal[2]) * 0.04
            s.shape("cube", "trim", box(c + np.asarray(offset, float), (hx, half[1], hz)))

    def _garden(self, s: Scene) -> None:
        s.bsdf("bark", bsdf("diffuse", (0.12, 0.08, 0.05)))
        s.bsdf("leaves", bsdf("diffuse", texture=bitmap("", self.tex["leaves"], (3, 3))))
        for k, (x, z, height) in enumerate(self.trees):
            s.shape("cylinder", "bark", p0=(x, 0, z), p1=(x, height * 0.6, z), radius=0.12)
            for dx, dy, dz, r in ((0, 0.75, 0, 0.35), (0.25, 0.95, 0.1, 0.25), (-0.2, 0.9, -0.15, 0.28)):
                s.shape("sphere", "leaves", center=(x + dx * height, dy * height, z + dz * height), radius=r * height)
        s.bsdf("fence", bsdf("roughplastic", (0.82, 0.82, 0.8), alpha=0.3))
        z = self.depth / 2 + 8.5
        for x in np.arange(-10, 10.01, 0.5):
            if abs(x) > 1.0:
                s.shape("cube", "fence", box((x, 0.5, z), (0.04, 0.5, 0.02)))
        for y in (0.3, 0.8):
            for sign in (-1, 1):
                s.shape("cube", "fence", box((sign * 5.5, y, z - 0.04), (4.5, 0.04, 0.02)))
        # a car on the drive: painted body, dark windows, tyres
        cx, cz = -self.width / 2 - 2.5, self.depth / 2 + 3
        s.bsdf("paint", bsdf("roughplastic", self.car_colour, alpha=0.05, int_ior=1.5))
        s.bsdf("tyre", bsdf("diffuse", (0.02, 0.02, 0.02)))
        s.bsdf("chrome", bsdf("conductor", material="Cr"))
        s.shape("cube", "paint", box((cx, 0.65, cz), (0.85, 0.35, 2.1)))
        s.shape("cube", "paint", box((cx, 1.2, cz - 0.2), (0.8, 0.25, 1.1)))
        s.shape("cube", "glass", box((cx, 1.2, cz - 0.2), (0.81, 0.2, 1.0)))
        for dz in (-1.3, 1.3):
            for dx in (-0.86, 0.86):
                s.shape(
                    "cylinder",
                    "tyre",
                    p0=(cx + dx - 0.1, 0.33, cz + dz),
                    p1=(cx + dx + 0.1, 0.33, cz + dz),
                    radius=0.33,
                )
                s.shape(
                    "disk", "chrome", frame((cx + dx * 1.13, 0.33, cz + dz), (np.sign(dx), 0, 0), (0, 1, 0), 0.18, 0.18)
                )

    def _camera(self, s: Scene, rng: np.random.Generator) -> None:
        drone = rng.uniform() < 0.3
        angle = rng.uniform(-math.pi * 0.75, math.pi * 0.75)  # mostly from the front and sides
        distance = rng.uniform(9.0, 15.0) if drone else rng.uniform(7.0, 13.0)
        eye = np.array(
            [
                distance * math.sin(angle),
                rng.uniform(6.0, 10.0) if drone else rng.uniform(1.4, 1.9),
                distance * math.cos(angle),
            ]
        )
        target = np.array([rng.uniform(-2, 2), rng.uniform(1.0, 3.0), rng.uniform(-1, 1)])
        s.camera(eye, target, rng.uniform(45, 65))


def write(out_dir: Path, seed: int, frames: int) -> list[Path]:
    house = House(seed, out_dir)
    paths = []
    for index in range(frames):
        path = out_dir / f"exterior-{seed}-{index:03d}.xml"
        house.frame(index).write(path)
        paths.append(path)
    return paths
