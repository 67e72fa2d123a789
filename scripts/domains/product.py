"""`product`: a product shot on a turntable. One set per seed (a glass bottle with a metal cap, a glazed
mug, a wooden box and a brushed-metal tin on a glossy turntable before a seamless paper sweep), turned
through a full revolution across the frames, seen from three camera heights under three softbox setups."""

from __future__ import annotations

import colorsys
import math
from pathlib import Path

import numpy as np

from . import assets
from .scenexml import Scene, area, bitmap, box, bsdf, frame, rotation_y, two_sided, warm_white

SETUPS = ("key-fill-rim", "top-soft", "low-hard")
CAMERAS = ((1.2, 0.4, 34.0), (1.35, 0.85, 32.0), (0.9, 0.22, 36.0))  # distance, height, fov


def _colour(rng: np.random.Generator, saturation, value) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*saturation), rng.uniform(*value)))


class Turntable:
    def __init__(self, seed: int, out_dir: Path):
        rng = np.random.default_rng([seed, 7101])
        self.seed = seed
        self.paper = _colour(rng, (0.0, 0.35), (0.55, 0.8))
        self.glaze = _colour(rng, (0.5, 0.95), (0.25, 0.7))
        self.tin = ("Al", "Cu", "Cr")[int(rng.integers(3))]
        self.cap = ("Au", "Cr", "Cu")[int(rng.integers(3))]

        def name(part):
            return out_dir / f"product-{seed}-{part}"

        bottle = np.concatenate(
            [np.full(10, 0.075), 0.075 - 0.05 * np.sin(np.linspace(0, math.pi / 2, 8)), np.full(4, 0.022)]
        )
        self.bottle_height = rng.uniform(0.22, 0.3)
        self.bottle = assets.write_obj(name("bottle.obj"), assets.lathe(bottle, self.bottle_height))
        self.band = assets.write_obj(name("band.obj"), assets.lathe(np.full(2, 0.0605), 0.05))
        mug = np.concatenate([[0.055], np.linspace(0.06, 0.07, 12)])
        self.mug = assets.write_obj(name("mug.obj"), assets.lathe(mug, 0.13))
        self.handle = assets.write_obj(
            name("handle.obj"), assets.prism([[0, -0.04], [0.03, -0.03], [0.03, 0.03], [0, 0.04]], 0.015)
        )
        self.cove = assets.write_obj(name("cove.obj"), assets.cove(1.0, 6.0))
        self.wood = assets.write_texture(name("wood.exr"), assets.wood_planks(rng, np.array([0.5, 0.3, 0.14]), 3))
        self.label = assets.write_texture(
            name("label.exr"),
            assets.wallpaper(rng, _colour(rng, (0.0, 0.2), (0.7, 0.85)), _colour(rng, (0.6, 1.0), (0.2, 0.5))),
        )
        self.layout = rng.uniform(0, 2 * math.pi)

    def frame(self, index: int, frames: int) -> Scene:
        setup = SETUPS[index % len(SETUPS)]
        distance, height, fov = CAMERAS[(index // len(SETUPS)) % len(CAMERAS)]
        turn = 2 * math.pi * index / frames
        s = Scene(f" product set {self.seed}, frame {index} ({setup}), written by scripts/make_domain_scenes.py ")
        self._studio(s)
        self._products(s, turn)
        self._lights(s, setup)
        s.camera((0, height, distance), (0, 0.12, 0), fov)
        return s

    def _studio(self, s: Scene) -> None:
        """A paper sweep: floor, a quarter-cylinder cove and a back wall, one surface to the eye."""
        s.bsdf("paper", bsdf("diffuse", self.paper))
        s.shape("rectangle", "paper", frame((0, 0, 0.5), (0, 1, 0), (0, 0, -1), 3.0, 2.0))
        radius, z_cove = 1.0, -1.5  # the floor runs to z_cove, curves up with `radius`, then the wall rises
        s.shape("obj", "paper", box((0, radius, z_cove), (1, 1, 1)), filename=self.cove)
        s.shape("rectangle", "paper", frame((0, radius + 1.5, z_cove - radius), (0, 0, 1), (0, 1, 0), 3.0, 1.5))
        s.bsdf("turntable", bsdf("roughplastic", (0.02, 0.02, 0.02), alpha=0.05))
        s.shape("cylinder", "turntable", p0=(0, 0, 0), p1=(0, 0.03, 0), radius=0.45)
        s.shape("disk", "turntable", frame((0, 0.03, 0), (0, 1, 0), (0, 0, -1), 0.45, 0.45))

    def _products(self, s: Scene, turn: float) -> None:
        spin = rotation_y(turn)

        def at(x, y, z):
            return (spin @ [x, y, z, 1.0])[:3]

        a = self.layout
        (bx, bz), (mx, mz), (wx, wz) = [(0.2 * math.cos(a + k * 2.1), 0.2 * math.sin(a + k * 2.1)) for k in range(3)]
        s.bsdf("glass", bsdf("dielectric", int_ior=1.5))
        s.bsdf("cap", bsdf("roughconductor", material=self.cap, alpha=0.08))
        s.shape("obj", "glass", spin @ box((bx, 0.03, bz), (1, 1, 1)), filename=self.bottle)
        top = 0.03 + self.bottle_height
        s.shape("cylinder", "cap", p0=at(bx, top - 0.005, bz), p1=at(bx, top + 0.05, bz), radius=0.03)
        s.shape("disk", "cap", frame(at(bx, top + 0.05, bz), (0, 1, 0), (0, 0, -1), 0.03, 0.03))
        s.bsdf("glaze", bsdf("plastic", self.glaze, int_ior=1.6))
        s.shape("obj", "glaze", spin @ box((mx, 0.03, mz), (1, 1, 1)), filename=self.mug)
        s.shape("obj", "glaze", spin @ box((mx + 0.085, 0.095, mz), (1, 1, 1)), filename=self.handle)
        s.bsdf("wood", bsdf("roughplastic", texture=bitmap("", self.wood, (1, 1)), alpha=0.15))
        s.shape("cube", "wood", spin @ box((wx, 0.03 + 0.06, wz), (0.09, 0.06, 0.07), 0.4))
        s.bsdf("tin", bsdf("roughconductor", material=self.tin, alpha=0.2))
        tx, tz = -0.05 * math.cos(a), -0.05 * math.sin(a)
        s.shape("cylinder", "tin", p0=at(tx, 0.03, tz), p1=at(tx, 0.12, tz), radius=0.06)
        s.shape("disk", "tin", frame(at(tx, 0.12, tz), (0, 1, 0), (0, 0, -1), 0.06, 0.06))
        s.bsdf("label", two_sided(bsdf("diffuse", texture=bitmap("", self.label, (1, 1)))))
        s.shape("obj", "label", spin @ box((tx, 0.05, tz), (1, 1, 1)), filename=self.band)

    def _lights(self, s: Scene, setup: str) -> None:
        s.bsdf("softbox", bsdf("diffuse", (0.0, 0.0, 0.0)))
        lights = {
            "key-fill-rim": [
                ((-1.2, 1.4, 1.0), 0.5, 0.5, 10.0, 0.2),
                ((1.6, 0.8, 1.4), 0.9, 0.7, 1.5, 0.0),
                ((0.6, 1.6, -1.2), 0.12, 0.8, 12.0, 0.0),
            ],
            "top-soft": [((0.0, 2.2, 0.3), 0.8, 0.8, 6.0, 0.1), ((-1.8, 0.6, 0.8), 0.5, 0.5, 1.5, 0.4)],
            "low-hard": [((1.3, 0.5, 0.9), 0.1, 0.1, 300.0, 0.8), ((-1.5, 1.8, -0.4), 0.6, 0.3, 4.0, 0.0)],
        }[setup]
        for position, half_u, half_v, radiance, warmth in lights:
            position = np.asarray(position, float)
            normal = (np.array([0, 0.2, 0]) - position) / np.linalg.norm(position - [0, 0.2, 0])
            up = np.cross(np.cross(normal, [0, 1, 0]), normal)
            s.shape(
                "rectangle",
                "softbox",
                frame(position, normal, up, half_u, half_v),
                emitter=area(warm_white(warmth) * radiance),
            )


def write(out_dir: Path, seed: int, frames: int) -> list[Path]:
    table = Turntable(seed, out_dir)
    paths = []
    for index in range(frames):
        path = out_dir / f"product-{seed}-{index:03d}.xml"
        table.frame(index, frames).write(path)
        paths.append(path)
    return paths
