"""`cbox`: Cornell-box-like interiors, each frame a scene of its own (a box of five walls open towards the
camera, coloured side walls, some surfaces checkered, a rectangular ceiling light of varied size and power,
every SMALL_LIGHT_EVERY-th one small and bright, and 1-4 objects: sphere, cube, capped cylinder, standing
disk or panel). Every DIFFUSE_ONLY_EVERY-th scene is purely diffuse; every other has at least one
rough/smooth plastic, rough/smooth conductor or glass object. Only Mitsuba's built-in shapes and its
checkerboard texture: no mesh or image files."""

from __future__ import annotations

import colorsys
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .scenexml import FILM, add, add_matrix, add_point, frame, rotation_x, rotation_y, translate_scale, triple

DIFFUSE_ONLY_EVERY = 3
SMALL_LIGHT_EVERY = 4
SPECULAR_KINDS = ("roughplastic", "plastic", "roughconductor", "conductor", "dielectric")
CLOSED_SHAPES = ("sphere", "cube", "cylinder")  # glass needs a closed surface
WHITE = (0.725, 0.71, 0.68)  # Mitsuba's Cornell box: walls, then its red and green
WALL_PAIRS = [
    ((0.63, 0.065, 0.05), (0.14, 0.45, 0.091)),
    ((0.08, 0.2, 0.6), (0.7, 0.6, 0.1)),
    ((0.75, 0.35, 0.08), (0.08, 0.45, 0.45)),
    ((0.4, 0.12, 0.55), (0.4, 0.6, 0.12)),
]
METALS = ("Au", "Ag", "Cu", "Al", "Cr")


def colour(rng: np.random.Generator, saturation=(0.2, 0.85), value=(0.3, 0.8)) -> tuple[float, ...]:
    return colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(*saturation), rng.uniform(*value))


def material(rng: np.random.Generator, kind: str, tint) -> ET.Element:
    """A BSDF element of `kind`; `tint` colours the diffuse part of diffuse and plastic kinds."""
    bsdf = ET.Element("bsdf", type=kind)
    if kind == "diffuse":
        add(bsdf, "rgb", "reflectance", tint)
    elif kind in ("plastic", "roughplastic"):
        add(bsdf, "rgb", "diffuse_reflectance", tint)
        if kind == "roughplastic":
            add(bsdf, "float", "alpha", rng.uniform(0.05, 0.3))
    elif kind == "roughconductor":
        add(bsdf, "string", "material", METALS[int(rng.integers(len(METALS)))])
        add(bsdf, "float", "alpha", rng.uniform(0.05, 0.35))
    elif kind == "conductor":
        add(bsdf, "string", "material", ("none", "Ag", "Al")[int(rng.integers(3))])  # none: a perfect mirror
    else:  # dielectric: glass, water or a dense glass
        add(bsdf, "float", "int_ior", (1.33, 1.5, 1.7)[int(rng.integers(3))])
    return bsdf


def checkerboard(rng: np.random.Generator, base, name: str) -> ET.Element:
    """A checkerboard texture on `base` and a darker or lighter shade of it."""
    texture = ET.Element("texture", type="checkerboard", name=name)
    other = np.clip(np.asarray(base) * rng.uniform(0.2, 0.5) if max(base) > 0.4 else np.asarray(base) + 0.4, 0, 0.85)
    add(texture, "rgb", "color0", base)
    add(texture, "rgb", "color1", other)
    checks = int(rng.integers(2, 6))  # the texture has 2x2 checks per unit of uv
    to_uv = ET.SubElement(texture, "transform", name="to_uv")
    ET.SubElement(to_uv, "scale", x=str(checks), y=str(checks))
    return texture


class Scene:
    """One cbox scene being written: an XML tree, with named BSDFs that shapes reference."""

    def __init__(self, comment: str):
        self.root = ET.Element("scene", version="3.0.0")
        self.root.append(ET.Comment(comment))
        self.specular = False

    def bsdf(self, name: str, bsdf: ET.Element) -> str:
        bsdf.set("id", name)
        self.root.append(bsdf)
        self.specular |= any(b.get("type") not in ("diffuse", "twosided") for b in bsdf.iter("bsdf"))
        return name

    def shape(self, kind: str, bsdf: str, to_world: np.ndarray | None = None, emitter=None, **points) -> None:
        shape = ET.SubElement(self.root, "shape", type=kind)
        if to_world is not None:
            add_matrix(shape, to_world)
        for name, value in points.items():
            if name == "radius":
                add(shape, "float", "radius", value)
            else:
                add_point(shape, name, value)
        ET.SubElement(shape, "ref", id=bsdf)
        if emitter is not None:
            shape.append(emitter)


def walls(rng: np.random.Generator, scene: Scene, size, diffuse_only: bool) -> None:
    """Floor, ceiling, back and two coloured side walls; maybe one checkered, maybe a glossy floor."""
    w, h, d = size
    roll = rng.uniform()
    if roll < 0.3:
        left, right = WALL_PAIRS[0]
    elif roll < 0.7:
        left, right = WALL_PAIRS[1 + int(rng.integers(len(WALL_PAIRS) - 1))]
    else:
        hue, sat, val = rng.uniform(), rng.uniform(0.5, 0.9), rng.uniform(0.45, 0.7)
        left = colorsys.hsv_to_rgb(hue, sat, val)
        right = colorsys.hsv_to_rgb((hue + 0.5) % 1.0, sat, val)
    if rng.uniform() < 0.5:
        left, right = right, left
    white = tuple(np.asarray(WHITE) * rng.uniform(0.8, 1.05))
    colours = {"floor": white, "ceiling": white, "back": white, "left": left, "right": right}
    placement = {  # name: (centre, inward normal, in-plane up, half sizes)
        "floor": ((0, 0, 0), (0, 1, 0), (0, 0, -1), (w / 2, d / 2)),
        "ceiling": ((0, h, 0), (0, -1, 0), (0, 0, 1), (w / 2, d / 2)),
        "back": ((0, h / 2, -d / 2), (0, 0, 1), (0, 1, 0), (w / 2, h / 2)),
        "left": ((-w / 2, h / 2, 0), (1, 0, 0), (0, 1, 0), (d / 2, h / 2)),
        "right": ((w / 2, h / 2, 0), (-1, 0, 0), (0, 1, 0), (d / 2, h / 2)),
    }
    checkered = ("floor", "floor", "back", "left", "right")[int(rng.integers(5))] if rng.uniform() < 0.4 else None
    glossy_floor = not diffuse_only and rng.uniform() < 0.2
    for name, (center, normal, up, (hu, hv)) in placement.items():
        kind = "roughplastic" if name == "floor" and glossy_floor else "diffuse"
        bsdf = material(rng, kind, colours[name])
        if name == checkered:
            for element in bsdf.findall("rgb"):
                bsdf.remove(element)
                bsdf.append(checkerboard(rng, colours[name], element.get("name")))
        scene.shape("rectangle", scene.bsdf(f"wall-{name}", bsdf), frame(center, normal, up, hu, hv))


def ceiling_light(rng: np.random.Generator, scene: Scene, size, small: bool) -> None:
    """A one-sided rectangle just under the ceiling, facing down; its power, not its radiance, is drawn,
    so a small light is a bright one."""
    w, h, d = size
    share = (0.05, 0.12) if small else (0.15, 0.4)
    half_x, half_z = w / 2 * rng.uniform(*share), d / 2 * rng.uniform(*share)
    cx = rng.uniform(-1, 1) * (w / 2 - half_x - 0.1) * 0.5
    cz = rng.uniform(-1, 1) * (d / 2 - half_z - 0.1) * 0.5
    power = 8.0 * 2.0 ** rng.uniform(-1.0, 1.0) * (w * d / 4.0)  # Mitsuba's Cornell box light: about 8
    warmth = rng.uniform()
    tint = np.array([1.0, 1.0 - 0.24 * warmth, 1.0 - 0.63 * warmth])  # white .. the classic box's orange
    tint /= tint @ np.array([0.2126, 0.7152, 0.0722])
    emitter = ET.Element("emitter", type="area")
    add(emitter, "rgb", "radiance", tint * power / (math.pi * 4 * half_x * half_z))
    light = scene.bsdf("light", material(rng, "diffuse", (0, 0, 0)))
    scene.shape("rectangle", light, frame((cx, h - 1e-3, cz), (0, -1, 0), (0, 0, 1), half_x, half_z), emitter=emitter)


def camera(rng: np.random.Generator, scene: Scene, size) -> tuple[np.ndarray, np.ndarray, float]:
    """A perspective camera just inside the open side, looking at the back wall. Returns its position,
    world-to-camera rotation (rows: right, up, forward) and tan(fov / 2)."""
    w, h, d = size
    fov = rng.uniform(55.0, 80.0)
    eye = np.array([rng.uniform(-0.12, 0.12) * w, rng.uniform(0.42, 0.58) * h, d / 2 - rng.uniform(0.0, 0.15)])
    target = np.array([rng.uniform(-0.1, 0.1) * w, rng.uniform(0.3, 0.5) * h, -d / 2])
    sensor = ET.SubElement(scene.root, "sensor", type="perspective")
    add(sensor, "float", "fov", fov)
    transform = ET.SubElement(sensor, "transform", name="to_world")
    ET.SubElement(transform, "lookat", origin=triple(eye), target=triple(target), up="0, 1, 0")
    sampler = ET.SubElement(sensor, "sampler", type="independent")
    add(sampler, "integer", "sample_count", 64)
    film = ET.SubElement(sensor, "film", type="hdrfilm")
    add(film, "integer", "width", FILM)
    add(film, "integer", "height", FILM)
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0, 1, 0])
    right /= np.linalg.norm(right)
    return eye, np.stack([right, np.cross(right, forward), forward]), math.tan(math.radians(fov) / 2)


def object_size(rng: np.random.Generator, kind: str) -> dict:
    """The shape's dimensions and its footprint radius on the floor (for non-overlapping placement)."""
    if kind == "sphere":
        r = rng.uniform(0.15, 0.38)
        return {"radius": r, "footprint": r, "height": 2 * r}
    if kind == "cube":
        half = rng.uniform(0.12, 0.32, size=2)
        tall = rng.uniform(0.12, 0.55)
        return {"half": (half[0], tall, half[1]), "footprint": float(np.hypot(*half)), "height": 2 * tall}
    if kind == "cylinder":
        r = rng.uniform(0.1, 0.28)
        return {"radius": r, "footprint": r, "height": rng.uniform(0.3, 1.0)}
    half = (rng.uniform(0.15, 0.4),) * 2 if kind == "disk" else (rng.uniform(0.15, 0.4), rng.uniform(0.2, 0.55))
    return {"half": half, "footprint": half[0], "height": 2 * half[1]}


def place(rng: np.random.Generator, size, view, footprint: float, height: float, taken: list) -> np.ndarray | None:
    """A floor position inside the box, clear of the other objects and in the camera's view; None if
    50 draws found none."""
    w, _, d = size
    eye, rotation, tan_half = view
    for _ in range(50):
        x = rng.uniform(-w / 2 + footprint + 0.05, w / 2 - footprint - 0.05)
        z = rng.uniform(-d / 2 + footprint + 0.05, d / 2 - footprint - 0.05)
        local = rotation @ (np.array([x, height / 2, z]) - eye)
        near = 1.2 + max(footprint, height / 2)  # a big object further away: none fills the frame
        seen = local[2] > near and max(abs(local[0]), abs(local[1])) < 0.8 * tan_half * local[2]
        if seen and all(math.hypot(x - px, z - pz) > footprint + pf + 0.05 for px, pz, pf in taken):
            taken.append((x, z, footprint))
            return np.array([x, 1e-3, z])  # just above the floor: no surface coincides with it
    return None


def add_object(rng: np.random.Generator, scene: Scene, index: int, kind: str, bsdf_kind: str, dims: dict, base) -> None:
    """Shape `kind` standing on the floor at `base`, in a material of `bsdf_kind`."""
    tint = colour(rng)
    bsdf = material(rng, bsdf_kind, tint)
    if kind in ("disk", "rectangle"):  # thin shapes are seen from both sides
        wrapper = ET.Element("bsdf", type="twosided")
        wrapper.append(bsdf)
        bsdf = wrapper
    name = scene.bsdf(f"object-{index}", bsdf)
    yaw = rng.uniform(-math.pi, math.pi)
    if kind == "sphere":
        scene.shape("sphere", name, center=base + [0, dims["radius"], 0], radius=dims["radius"])
    elif kind == "cube":
        offset, scale = translate_scale(base + [0, dims["half"][1], 0], dims["half"])
        scene.shape("cube", name, offset @ rotation_y(yaw) @ scale)
    elif kind == "cylinder":
        top = base + [0, dims["height"], 0]
        scene.shape("cylinder", name, p0=base, p1=top, radius=dims["radius"])
        scene.shape("disk", name, frame(top, (0, 1, 0), (0, 0, -1), dims["radius"], dims["radius"]))
        scene.shape("disk", name, frame(base, (0, -1, 0), (0, 0, 1), dims["radius"], dims["radius"]))
    else:  # a disk or panel on its edge, turned 20-57 degrees from the camera (a mirror facing it would
        lean = -rng.uniform(0.0, 0.35)  # show only the black open side) and maybe leaning back
        turn = math.copysign(rng.uniform(0.35, 1.0), yaw)
        half_u, half_v = dims["half"]
        offset, scale = translate_scale(base + [0, half_v * math.cos(lean), 0], (half_u, half_v, 1.0))
        scene.shape(kind, name, offset @ rotation_y(turn) @ rotation_x(lean) @ scale)


def material_kind(rng: np.random.Generator, kind: str, diffuse_only: bool, first: bool) -> str:
    """Diffuse in a diffuse-only scene; else the first object placed is specular, the others anything."""
    if diffuse_only:
        return "diffuse"
    choices = SPECULAR_KINDS if first else ("diffuse",) + SPECULAR_KINDS
    choices = tuple(c for c in choices if kind in CLOSED_SHAPES or c != "dielectric")
    return choices[int(rng.integers(len(choices)))]


def objects(rng: np.random.Generator, scene: Scene, size, view, diffuse_only: bool) -> int:
    """1-4 objects on the floor (fewer where no free place is found); returns how many."""
    kinds = ("sphere", "cube", "cylinder", "disk", "rectangle")
    taken: list = []
    placed = 0
    for index in range(int(rng.integers(1, 5))):
        kind = kinds[int(rng.integers(len(kinds)))]
        dims = object_size(rng, kind)
        base = place(rng, size, view, dims["footprint"], dims["height"], taken)
        if base is not None:
            bsdf_kind = material_kind(rng, kind, diffuse_only, first=placed == 0)
            add_object(rng, scene, index, kind, bsdf_kind, dims, base)
            placed += 1
    return placed


def cbox(seed: int, index: int) -> tuple[ET.Element, bool]:
    """Scene `index` of `seed` and whether it has a specular material."""
    rng = np.random.default_rng([seed, index])
    diffuse_only = index % DIFFUSE_ONLY_EVERY == DIFFUSE_ONLY_EVERY - 1
    scene = Scene(f" cbox scene {index} of seed {seed}, written by scripts/make_domain_scenes.py ")
    integrator = ET.SubElement(scene.root, "integrator", type="path")
    add(integrator, "integer", "max_depth", 8)
    size = (rng.uniform(1.8, 2.6), rng.uniform(1.8, 2.4), rng.uniform(2.0, 2.8))  # width, height, depth
    view = camera(rng, scene, size)
    walls(rng, scene, size, diffuse_only)
    ceiling_light(rng, scene, size, small=index % SMALL_LIGHT_EVERY == 1)
    placed = 0
    while not placed:  # a draw that placed nothing is redrawn
        placed = objects(rng, scene, size, view, diffuse_only)
    return scene.root, scene.specular


def write(out_dir: Path, seed: int, frames: int) -> list[Path]:
    paths = []
    for index in range(frames):
        root, _ = cbox(seed, index)
        ET.indent(root)
        path = out_dir / f"cbox-{seed}-{index:03d}.xml"
        path.write_text(ET.tostring(root, encoding="unicode") + "\n")
        paths.append(path)
    return paths
