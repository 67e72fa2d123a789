"""`interior`: one furnished living room (the set of a seed) seen from many cameras under three lighting
states: day (sun and sky through the window), dusk (sky only, downlights on), night (downlights and a
floor lamp). What a studio fine-tunes on: one set, its materials and textures in every frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import assets
from .scenexml import Scene, area, bitmap, box, bsdf, frame, sun_direction, two_sided, warm_white

STATES = ("day", "dusk", "night")
HEIGHT = 2.7
DAYLIGHT = 10.0  # sunsky scale: a room lit through one window is about as bright as under its lamps
SUN_SHARE = 0.35  # the sun's scale relative to the sky's: a soft day, whose references converge in a few thousand spp


class Room:
    """The set: sizes, colours and texture files drawn once per seed; `frame(i)` writes camera i."""

    def __init__(self, seed: int, out_dir: Path):
        rng = np.random.default_rng([seed, 7001])
        self.seed, self.rng = seed, rng
        self.width, self.depth = rng.uniform(5.0, 6.0), rng.uniform(4.2, 5.0)
        self.window = (rng.uniform(-0.5, 0.1), rng.uniform(2.0, 2.5), 0.55, 2.35)  # z centre, width, sill, top

        def tex(name, image):
            return assets.write_texture(out_dir / f"interior-{seed}-{name}.exr", image)

        self.textures = {
            "floor": tex("floor", assets.wood_planks(rng, np.array([0.55, 0.33, 0.16]) * rng.uniform(0.7, 1.2))),
            "table": tex("table", assets.wood_planks(rng, np.array([0.4, 0.22, 0.1]) * rng.uniform(0.7, 1.2), 2)),
            "sofa": tex("sofa", assets.fabric(rng, assets_colour(rng, (0.2, 0.6), (0.25, 0.6)))),
            "rug": tex(
                "rug",
                assets.tiles(
                    rng, assets_colour(rng, (0.3, 0.8), (0.3, 0.7)), 6, grout=assets_colour(rng, (0.1, 0.4), (0.6, 0.8))
                ),
            ),
            "wallpaper": tex(
                "wallpaper",
                assets.wallpaper(
                    rng, assets_colour(rng, (0.05, 0.3), (0.6, 0.8)), assets_colour(rng, (0.3, 0.7), (0.3, 0.6))
                ),
            ),
            "marble": tex("marble", assets.marble(rng)),
            "painting": tex("painting", assets.painting(rng)),
            "leaves": tex("leaves", assets.leaves(rng)),
            "grass": tex("grass", assets.grass(rng)),
        }
        self.vase = assets.write_obj(
            out_dir / f"interior-{seed}-vase.obj",
            assets.lathe(
                0.02 + 0.09 * np.sin(np.linspace(0.3, 2.8, 24)) ** rng.uniform(0.5, 1.5), rng.uniform(0.3, 0.45)
            ),
        )
        self.pot = assets.write_obj(out_dir / f"interior-{seed}-pot.obj", assets.lathe(np.linspace(0.14, 0.2, 8), 0.35))
        self.paint = assets_colour(rng, (0.02, 0.15), (0.65, 0.82))
        self.vase_colour = assets_colour(rng, (0.4, 0.9), (0.3, 0.7))
        self.books = [
            (assets_colour(rng, (0.3, 0.9), (0.15, 0.7)), rng.uniform(0.18, 0.3), rng.uniform(0.025, 0.05))
            for _ in range(60)
        ]
        self.sun = [(rng.uniform(55, 125), rng.uniform(18, 45)) for _ in range(4)]
        self.obstacles: list[tuple[float, float, float, float, float]] = []  # x0, x1, z0, z1, height

    def frame(self, index: int) -> Scene:
        state = STATES[index % len(STATES)]
        rng = np.random.default_rng([self.seed, 7002, index])
        scene = Scene(f" interior set {self.seed}, frame {index} ({state}), written by scripts/make_domain_scenes.py ")
        self.obstacles = []
        self._shell(scene)
        self._furniture(scene)
        self._lights(scene, state, index)
        self._camera(scene, rng)
        return scene

    # -- the room --------------------------------------------------------------------------------------
    def _shell(self, s: Scene) -> None:
        w, d, h = self.width, self.depth, HEIGHT
        s.bsdf("floor", bsdf("roughplastic", texture=bitmap("", self.textures["floor"], (w / 2.0, d / 2.0)), alpha=0.2))
        s.bsdf("paint", bsdf("diffuse", self.paint))
        s.bsdf("ceiling", bsdf("diffuse", (0.78, 0.78, 0.76)))
        s.bsdf("wallpaper", bsdf("diffuse", texture=bitmap("", self.textures["wallpaper"], (d / 1.5, h / 1.5))))
        s.shape("rectangle", "floor", frame((0, 0, 0), (0, 1, 0), (0, 0, -1), w / 2, d / 2))
        s.shape("rectangle", "ceiling", frame((0, h, 0), (0, -1, 0), (0, 0, 1), w / 2, d / 2))
        s.shape("rectangle", "paint", frame((0, h / 2, -d / 2), (0, 0, 1), (0, 1, 0), w / 2, h / 2))
        s.shape("rectangle", "paint", frame((0, h / 2, d / 2), (0, 0, -1), (0, 1, 0), w / 2, h / 2))
        s.shape("rectangle", "wallpaper", frame((-w / 2, h / 2, 0), (1, 0, 0), (0, 1, 0), d / 2, h / 2))
        zc, width, sill, top = self.window
        z0, z1 = zc - width / 2, zc + width / 2
        x = w / 2
        for za, zb, ya, yb in (
            (-d / 2, d / 2, 0, sill),
            (-d / 2, d / 2, top, h),
            (-d / 2, z0, sill, top),
            (z1, d / 2, sill, top),
        ):
            s.shape(
                "rectangle",
                "paint",
                frame((x, (ya + yb) / 2, (za + zb) / 2), (-1, 0, 0), (0, 1, 0), (zb - za) / 2, (yb - ya) / 2),
            )
        s.bsdf("lawn", bsdf("diffuse", texture=bitmap("", self.textures["grass"], (20, 20))))
        s.shape("rectangle", "lawn", frame((0, -0.01, 0), (0, 1, 0), (0, 0, -1), 40, 40))  # seen through the window
        s.bsdf("frame-white", bsdf("roughplastic", (0.8, 0.8, 0.78), alpha=0.2))
        s.shape("cube", "frame-white", box((x - 0.05, sill - 0.02, zc), (0.08, 0.02, width / 2 + 0.06)))
        for za in (z0 - 0.03, z1 + 0.03):  # the reveal's sides: the wall's thickness
            s.shape("cube", "frame-white", box((x + 0.1, (sill + top) / 2, za), (0.1, (top - sill) / 2, 0.03)))
        s.shape("cube", "frame-white", box((x + 0.1, top + 0.03, zc), (0.1, 0.03, width / 2 + 0.06)))

    def _block(self, s: Scene, name: str, centre, half, yaw: float = 0.0, solid: bool = True) -> None:
        s.shape("cube", name, box(centre, half, yaw))
        if solid:
            c, r = np.asarray(centre), max(half[0], half[2])
            self.obstacles.append((c[0] - r, c[0] + r, c[2] - r, c[2] + r, c[1] + half[1]))

    def _furniture(self, s: Scene) -> None:
        w, d = self.width, self.depth
        left, back, front = -w / 2, -d / 2, d / 2
        s.bsdf("sofa", bsdf("diffuse", texture=bitmap("", self.textures["sofa"], (3, 3))))
        sx = left + 0.55
        self._block(s, "sofa", (sx, 0.22, 0), (0.45, 0.22, 1.0))
        self._block(s, "sofa", (left + 0.17, 0.45, 0), (0.12, 0.45, 1.0))
        for z in (-1.05, 1.05):
            self._block(s, "sofa", (sx, 0.3, z), (0.45, 0.3, 0.1))
        for z in (-0.5, 0.5):
            self._block(s, "sofa", (sx + 0.05, 0.5, z), (0.38, 0.07, 0.47), solid=False)
        # rug, coffee table on chrome legs
        s.bsdf("rug", two_sided(bsdf("diffuse", texture=bitmap("", self.textures["rug"], (1, 1)))))
        s.shape("rectangle", "rug", frame((left + 1.6, 0.003, 0), (0, 1, 0), (0, 0, -1), 0.9, 1.3))
        s.bsdf("table-wood", bsdf("roughplastic", texture=bitmap("", self.textures["table"], (1, 1)), alpha=0.06))
        s.bsdf("chrome", bsdf("roughconductor", material="Cr", alpha=0.04))
        tx = left + 1.7
        self._block(s, "table-wood", (tx, 0.42, 0), (0.35, 0.025, 0.6))
        for dx in (-0.3, 0.3):
            for dz in (-0.52, 0.52):
                s.shape("cylinder", "chrome", p0=(tx + dx, 0, dz), p1=(tx + dx, 0.4, dz), radius=0.015)
        # a glass vase and a ceramic one on the table
        s.bsdf("glass", bsdf("dielectric", int_ior=1.5))
        s.bsdf("ceramic", bsdf("plastic", self.vase_colour))
        s.shape("obj", "ceramic", box((tx + 0.1, 0.445, -0.25), (1, 1, 1)), filename=self.vase)
        s.shape("sphere", "glass", center=(tx - 0.1, 0.53, 0.25), radius=0.085)
        # bookshelf against the back wall
        s.bsdf("shelf", bsdf("roughplastic", (0.75, 0.74, 0.7), alpha=0.3))
        bx = 0.6
        for dx in (-0.62, 0.62):
            self._block(s, "shelf", (bx + dx, 1.0, back + 0.16), (0.02, 1.0, 0.15))
        for k in range(5):
            self._block(s, "shelf", (bx, 0.02 + 0.45 * k, back + 0.16), (0.6, 0.015, 0.15), solid=False)
        books = iter(self.books)
        for k in range(4):
            x = bx - 0.58
            while True:
                colour, tall, thick = next(books, self.books[0])
                if x + 2 * thick > bx + 0.58:
                    break
                name = f"book-{k}-{round(x * 100)}"
                s.bsdf(
                    name,
                    bsdf(
                        "roughplastic" if tall > 0.24 else "diffuse", colour, **({"alpha": 0.25} if tall > 0.24 else {})
                    ),
                )
                s.shape(
                    "cube",
                    name,
                    box((x + thick, 0.035 + 0.45 * k + tall / 2, back + 0.17), (thick * 0.95, tall / 2, 0.11)),
                )
                x += 2 * thick
        # dining table with a marble top, two chairs
        s.bsdf("marble", bsdf("roughplastic", texture=bitmap("", self.textures["marble"], (1, 1)), alpha=0.03))
        s.bsdf("black", bsdf("roughplastic", (0.03, 0.03, 0.03), alpha=0.15))
        dx, dz = w / 2 - 1.3, back + 1.2
        s.shape("cylinder", "marble", p0=(dx, 0.72, dz), p1=(dx, 0.75, dz), radius=0.55)
        s.shape("disk", "marble", frame((dx, 0.75, dz), (0, 1, 0), (0, 0, -1), 0.55, 0.55))
        s.shape("cylinder", "black", p0=(dx, 0, dz), p1=(dx, 0.72, dz), radius=0.05)
        self.obstacles.append((dx - 0.55, dx + 0.55, dz - 0.55, dz + 0.55, 0.75))
        for side in (-1, 1):
            cx = dx + side * 0.75
            self._block(s, "table-wood", (cx, 0.45, dz), (0.2, 0.02, 0.2))
            self._block(s, "table-wood", (cx + side * 0.18, 0.7, dz), (0.02, 0.25, 0.2))
            for lx in (-0.17, 0.17):
                for lz in (-0.17, 0.17):
                    s.shape("cylinder", "black", p0=(cx + lx, 0, dz + lz), p1=(cx + lx, 0.43, dz + lz), radius=0.015)
        # a mirror on the front wall, a painting over the sofa, a plant by the window
        s.bsdf("mirror", bsdf("conductor", material="Ag"))
        s.shape("rectangle", "mirror", frame((-0.4, 1.5, front - 0.01), (0, 0, -1), (0, 1, 0), 0.5, 0.7))
        s.shape("cube", "black", box((-0.4, 1.5, front - 0.005), (0.54, 0.74, 0.004)))
        s.bsdf("painting", bsdf("diffuse", texture=bitmap("", self.textures["painting"], (1, 1))))
        s.shape("rectangle", "painting", frame((left + 0.01, 1.6, 0), (1, 0, 0), (0, 1, 0), 0.6, 0.4))
        s.bsdf("terracotta", bsdf("diffuse", (0.5, 0.22, 0.12)))
        s.bsdf("leaves", bsdf("diffuse", texture=bitmap("", self.textures["leaves"], (2, 2))))
        px, pz = w / 2 - 0.45, self.window[0] + self.window[1] / 2 + 0.45
        s.shape("obj", "terracotta", box((px, 0, pz), (1, 1, 1)), filename=self.pot)
        for k, (ox, oy, oz, r) in enumerate(((0, 0.75, 0, 0.28), (0.12, 1.0, 0.05, 0.2), (-0.1, 0.95, -0.08, 0.22))):
            s.shape("sphere", "leaves", center=(px + ox, oy, pz + oz), radius=r)
        self.obstacles.append((px - 0.3, px + 0.3, pz - 0.3, pz + 0.3, 1.2))

    # -- light -----------------------------------------------------------------------------------------
    def _lights(self, s: Scene, state: str, index: int) -> None:
        w, d = self.width, self.depth
        if state != "night":
            azimuth, elevation = self.sun[index % len(self.sun)]
            s.sunsky(
                sun_direction(azimuth, elevation),
                turbidity=3.0,
                sun_scale=DAYLIGHT * SUN_SHARE if state == "day" else 0.0,
                sky_scale=DAYLIGHT if state == "day" else DAYLIGHT / 3,
            )
        on = state != "day"
        s.bsdf("emitter-body", bsdf("diffuse", (0.0, 0.0, 0.0)))
        for x in (-w / 4, w / 4):
            for z in (-d / 4, d / 4):
                s.shape(
                    "disk",
                    "emitter-body",
                    frame((x, HEIGHT - 0.001, z), (0, -1, 0), (0, 0, 1), 0.15, 0.15),
                    emitter=area(warm_white(0.5) * 13.0) if on else None,
                )  # broad panels: few fireflies
        lx, lz = -w / 2 + 0.4, -d / 2 + 0.4
        s.shape("cylinder", "chrome", p0=(lx, 0, lz), p1=(lx, 1.45, lz), radius=0.015)
        s.shape("disk", "chrome", frame((lx, 0.01, lz), (0, 1, 0), (0, 0, -1), 0.16, 0.16))
        s.bsdf("shade", two_sided(bsdf("diffuse", (0.85, 0.8, 0.68))))
        s.shape("cylinder", "shade", p0=(lx, 1.35, lz), p1=(lx, 1.65, lz), radius=0.2)
        s.shape(
            "sphere",
            "emitter-body",
            center=(lx, 1.5, lz),
            radius=0.08,
            emitter=area(warm_white(1.0) * 16.0) if state == "night" else None,
        )
        self.obstacles.append((lx - 0.25, lx + 0.25, lz - 0.25, lz + 0.25, 1.7))

    # -- camera ----------------------------------------------------------------------------------------
    def _camera(self, s: Scene, rng: np.random.Generator) -> None:
        w, d = self.width, self.depth
        zc = self.window[0]
        anchors = [
            (-w / 2 + 0.6, 0.5, 0),
            (-w / 2 + 1.7, 0.45, 0),
            (0.6, 1.0, -d / 2 + 0.2),
            (w / 2 - 1.3, 0.75, -d / 2 + 1.2),
            (-0.4, 1.5, d / 2),
            (-w / 2, 1.6, 0),
            (w / 2 - 0.45, 0.8, zc + 1.2),
            (-w / 2 + 0.4, 1.4, -d / 2 + 0.4),
            (w / 2, 1.5, zc),
        ]  # the window last: close-ups leave it out (they would look out of it)
        close = rng.uniform() < 0.25  # a close-up of one piece, else a view across the room
        for _ in range(500):
            eye = np.array(
                [rng.uniform(-w / 2 + 0.4, w / 2 - 0.4), rng.uniform(0.9, 1.8), rng.uniform(-d / 2 + 0.4, d / 2 - 0.3)]
            )
            target = np.asarray(anchors[int(rng.integers(len(anchors) - close))], float) + rng.uniform(-0.3, 0.3, 3)
            distance = np.linalg.norm(target - eye)
            blocked = any(
                x0 - 0.25 < eye[0] < x1 + 0.25 and z0 - 0.25 < eye[2] < z1 + 0.25 and eye[1] < top + 0.3
                for x0, x1, z0, z1, top in self.obstacles
            )
            if not blocked and (1.0 < distance < 1.7 if close else distance > 2.6):
                break
        fov = rng.uniform(35, 48) if close else rng.uniform(50, 75)
        s.camera(eye, target, fov)


def assets_colour(rng: np.random.Generator, saturation, value) -> np.ndarray:
    import colorsys

    return np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*saturation), rng.uniform(*value)))


def write(out_dir: Path, seed: int, frames: int) -> list[Path]:
    room = Room(seed, out_dir)
    paths = []
    for index in range(frames):
        path = out_dir / f"interior-{seed}-{index:03d}.xml"
        room.frame(index).write(path)
        paths.append(path)
    return paths
