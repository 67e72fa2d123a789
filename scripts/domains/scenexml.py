"""Writing Mitsuba 3 XML scenes with ElementTree: typed properties, transforms, named BSDFs, shapes,
cameras and lights. Every domain generator builds its frames with `Scene`."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

FILM = 256  # the film the XML names; admc renders at render.resolution unless corpus.xml_resolution = "film"


def number(x: float) -> str:
    return f"{round(float(x), 4) + 0.0:.4f}"  # + 0.0: no "-0.0000"


def triple(values) -> str:
    return ", ".join(number(v) for v in values)


def add(parent: ET.Element, tag: str, name: str, value) -> ET.Element:
    """A typed property: <float name=... value=...>, <rgb ...>, <string ...> or <integer ...>."""
    text = {"float": number, "rgb": triple}.get(tag, str)(value)
    return ET.SubElement(parent, tag, name=name, value=text)


def add_point(parent: ET.Element, name: str, xyz, tag: str = "point") -> None:
    ET.SubElement(parent, tag, name=name, x=number(xyz[0]), y=number(xyz[1]), z=number(xyz[2]))


def add_matrix(parent: ET.Element, matrix: np.ndarray, name: str = "to_world") -> None:
    transform = ET.SubElement(parent, "transform", name=name)
    ET.SubElement(transform, "matrix", value=" ".join(number(v) for v in np.asarray(matrix).reshape(-1)))


def frame(center, normal, v, half_u: float, half_v: float) -> np.ndarray:
    """The to_world of a rectangle or disk (local x, y scaled to half_u, half_v; local +z onto `normal`),
    right-handed so that u x v = normal."""
    n, v = np.asarray(normal, float), np.asarray(v, float)
    n, v = n / np.linalg.norm(n), v / np.linalg.norm(v)
    u = np.cross(v, n)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = u * half_u, v * half_v, n, center
    return m


def rotation_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]], float)


def rotation_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]], float)


def translate_scale(offset, scale) -> tuple[np.ndarray, np.ndarray]:
    return (
        np.block([[np.eye(3), np.reshape(np.asarray(offset, float), (3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]),
        np.diag([*scale, 1.0]),
    )


def box(center, half, yaw: float = 0.0) -> np.ndarray:
    """The to_world of Mitsuba's cube ([-1, 1]^3) as a box of half extents `half`, turned by `yaw` about +y."""
    offset, scale = translate_scale(center, half)
    return offset @ rotation_y(yaw) @ scale


def bitmap(name: str, filename: str, repeat=(1.0, 1.0)) -> ET.Element:
    """A <texture type="bitmap"> property called `name`, tiled `repeat` times across the shape's uv."""
    texture = ET.Element("texture", type="bitmap", name=name)
    add(texture, "string", "filename", filename)
    to_uv = ET.SubElement(texture, "transform", name="to_uv")
    ET.SubElement(to_uv, "scale", x=number(repeat[0]), y=number(repeat[1]))
    return texture


def bsdf(kind: str, colour=None, texture: ET.Element | None = None, **values) -> ET.Element:
    """A BSDF of `kind`; its albedo (reflectance / diffuse_reflectance) is `colour` or `texture`;
    other float or string parameters as keywords (alpha=0.1, material="Au", int_ior=1.5)."""
    element = ET.Element("bsdf", type=kind)
    slot = "reflectance" if kind == "diffuse" else "diffuse_reflectance"
    if texture is not None:
        texture.set("name", slot)
        element.append(texture)
    elif colour is not None:
        add(element, "rgb", "specular_reflectance" if kind == "conductor" else slot, colour)
    for name, value in values.items():
        add(element, "string" if isinstance(value, str) else "float", name, value)
    return element


def two_sided(inner: ET.Element) -> ET.Element:
    wrapper = ET.Element("bsdf", type="twosided")
    wrapper.append(inner)
    return wrapper


def area(radiance) -> ET.Element:
    emitter = ET.Element("emitter", type="area")
    add(emitter, "rgb", "radiance", radiance)
    return emitter


def warm_white(kelvin_mix: float) -> np.ndarray:
    """An RGB tint of unit luminance between neutral white (0) and a warm incandescent (1)."""
    tint = np.array([1.0, 1.0 - 0.24 * kelvin_mix, 1.0 - 0.63 * kelvin_mix])
    return tint / (tint @ np.array([0.2126, 0.7152, 0.0722]))


class Scene:
    """One frame being written: an XML tree with named BSDFs that shapes reference."""

    def __init__(self, comment: str, max_depth: int = 8):
        self.root = ET.Element("scene", version="3.0.0")
        self.root.append(ET.Comment(comment))
        integrator = ET.SubElement(self.root, "integrator", type="path")
        add(integrator, "integer", "max_depth", max_depth)
        self.specular = False
        self.names: set[str] = set()

    def bsdf(self, name: str, element: ET.Element) -> str:
        """Declare a named BSDF once (later calls with the same name reuse it)."""
        if name not in self.names:
            element.set("id", name)
            self.root.append(element)
            self.names.add(name)
            self.specular |= any(b.get("type") not in ("diffuse", "twosided") for b in element.iter("bsdf"))
        return name

    def shape(self, kind: str, bsdf: str, to_world: np.ndarray | None = None, emitter=None, **values) -> ET.Element:
        """A shape of `kind`; keywords: radius (float), filename (string), flip_normals (bool), points."""
        shape = ET.SubElement(self.root, "shape", type=kind)
        if to_world is not None:
            add_matrix(shape, to_world)
        for name, value in values.items():
            if name == "radius":
                add(shape, "float", name, value)
            elif name == "filename":
                add(shape, "string", name, value)
            elif isinstance(value, bool):
                add(shape, "boolean", name, str(value).lower())
            else:
                add_point(shape, name, value)
        ET.SubElement(shape, "ref", id=bsdf)
        if emitter is not None:
            shape.append(emitter)
        return shape

    def camera(self, eye, target, fov: float, up=(0, 1, 0)) -> None:
        sensor = ET.SubElement(self.root, "sensor", type="perspective")
        add(sensor, "float", "fov", fov)
        transform = ET.SubElement(sensor, "transform", name="to_world")
        ET.SubElement(transform, "lookat", origin=triple(eye), target=triple(target), up=triple(up))
        sampler = ET.SubElement(sensor, "sampler", type="independent")
        add(sampler, "integer", "sample_count", 64)
        film = ET.SubElement(sensor, "film", type="hdrfilm")
        add(film, "integer", "width", FILM)
        add(film, "integer", "height", FILM)

    def sunsky(self, sun_direction, turbidity: float, sun_scale: float, sky_scale: float, albedo: float = 0.2) -> None:
        """Mitsuba's analytic sun and sky; `sun_direction` (towards the sun) in the scenes' y-up world."""
        emitter = ET.SubElement(self.root, "emitter", type="sunsky")
        add_point(emitter, "sun_direction", sun_direction, tag="vector")
        add(emitter, "float", "turbidity", turbidity)
        add(emitter, "float", "albedo", albedo)
        add(emitter, "float", "sun_scale", sun_scale)
        add(emitter, "float", "sky_scale", sky_scale)
        add_matrix(emitter, np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]))  # its +z onto +y

    def write(self, path: Path) -> None:
        ET.indent(self.root)
        path.write_text(ET.tostring(self.root, encoding="unicode") + "\n")


def sun_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    a, e = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
