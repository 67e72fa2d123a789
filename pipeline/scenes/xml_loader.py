"""User Mitsuba XML scenes: discovery, loading with our film, and the bytes that identify them.

A user's file may carry any film, reconstruction filter or integrator. We parse it with
ElementTree, swap every sensor's film for an `hdrfilm` with a `box` filter (a Gaussian splats
samples across pixels, which denoisers handle badly), rewrite referenced file names to absolute
paths and load the result with `mi.load_string`. Referenced files are checked up front so a
missing mesh is reported by name instead of as a parser error deep inside Mitsuba.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path

from .spec import XML_FAMILY, SceneError, SceneSpec

DEFAULT_RESOLUTION = (768, 576)  # Mitsuba's hdrfilm default, used when the XML gives none
_REFERENCE = re.compile(r"\$(\w+)")


def _parse(path: Path) -> ET.Element:
    if not path.is_file():
        raise SceneError(f"{path}: scene file not found")
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as error:
        raise SceneError(f"{path}: malformed XML ({error})") from error


def _defaults(root: ET.Element) -> dict[str, str]:
    return {d.get("name"): d.get("value", "") for d in root.iter("default") if d.get("name")}


def _substitute(text: str, defaults: dict[str, str], path: Path) -> str:
    def replace(match: re.Match) -> str:
        if match.group(1) not in defaults:
            raise SceneError(f"{path}: ${match.group(1)} is used but has no <default>")
        return defaults[match.group(1)]

    return _REFERENCE.sub(replace, text)


def _sensors(root: ET.Element, path: Path) -> list[ET.Element]:
    if root.tag != "scene":
        raise SceneError(f"{path}: root element is <{root.tag}>, expected <scene>")
    sensors = list(root.iter("sensor"))
    if not sensors:
        raise SceneError(f"{path}: the scene has no <sensor> (camera)")
    return sensors


def xml_resolution(path: str | Path) -> tuple[int, int]:
    """The film size the XML itself asks for (first sensor), Mitsuba's default if it gives none."""
    path = Path(path)
    root = _parse(path)
    defaults = _defaults(root)
    film = _sensors(root, path)[0].find("film")
    size = list(DEFAULT_RESOLUTION)
    for element in film.findall("integer") if film is not None else []:
        if element.get("name") in ("width", "height"):
            value = _substitute(element.get("value", ""), defaults, path)
            try:
                size[0 if element.get("name") == "width" else 1] = int(value)
            except ValueError as error:
                raise SceneError(f"{path}: film {element.get('name')} {value!r} is not an integer") from error
    return size[0], size[1]


def _filename_slots(root: ET.Element):
    """(element, attribute) pairs that hold a file name: <string name="filename" value=...>,
    and a `filename` attribute (<include>, <spectrum>)."""
    for element in root.iter():
        if element.tag == "string" and element.get("name") == "filename":
            yield element, "value"
        elif "filename" in element.attrib:
            yield element, "filename"


def _referenced_files(path: Path, root: ET.Element, seen: set[Path] | None = None) -> list[tuple[ET.Element, str, Path]]:
    """Every file the scene references (through includes too), resolved next to the file that names it."""
    seen = set() if seen is None else seen
    defaults = _defaults(root)
    found = []
    for element, attribute in _filename_slots(root):
        name = _substitute(element.get(attribute, ""), defaults, path)
        target = (path.parent / name).resolve()
        if not target.is_file():
            raise SceneError(f"{path}: referenced file {name!r} not found (looked for {target})")
        found.append((element, attribute, target))
        if element.tag == "include" and target not in seen:
            seen.add(target)
            found += _referenced_files(target, _parse(target), seen)
    return found


def _hdr_film(width: int, height: int) -> ET.Element:
    film = ET.Element("film", type="hdrfilm")
    ET.SubElement(film, "integer", name="width", value=str(width))
    ET.SubElement(film, "integer", name="height", value=str(height))
    ET.SubElement(film, "string", name="pixel_format", value="rgb")
    ET.SubElement(film, "rfilter", type="box")
    return film


def prepared_xml(path: str | Path, resolution: tuple[int, int] | None) -> str:
    """The scene's XML with our film in every sensor and absolute file names."""
    path = Path(path)
    root = _parse(path)
    sensors = _sensors(root, path)
    width, height = resolution if resolution is not None else xml_resolution(path)
    own_slots = {id(element) for element, _ in _filename_slots(root)}
    for element, attribute, target in _referenced_files(path, root):
        if id(element) in own_slots:  # included files keep theirs; the resolver finds them
            element.set(attribute, str(target))
    for sensor in sensors:
        for film in sensor.findall("film"):
            sensor.remove(film)
        sensor.append(_hdr_film(int(width), int(height)))
    return ET.tostring(root, encoding="unicode")


def load_xml_scene(path: str | Path, resolution: tuple[int, int] | None = None):
    """Load a user scene with an hdrfilm + box filter at `resolution` (None keeps the XML's).

    Included files may name files relative to themselves, so the scene's folder is also put on
    Mitsuba's (process-wide) file resolver for the duration of the load.
    """
    import mitsuba as mi

    path = Path(path).resolve()
    text = prepared_xml(path, resolution)
    saved = mi.FileResolver(mi.file_resolver())
    mi.file_resolver().prepend(str(path.parent))
    try:
        return mi.load_string(text, optimize=False)  # merging reorders shapes per load (see loading.py)
    except RuntimeError as error:
        raise SceneError(f"{path}: Mitsuba could not load the scene: {error}") from error
    finally:
        mi.set_file_resolver(saved)


def xml_content_bytes(path: str | Path, resolution: tuple[int, int] | None) -> bytes:
    """The XML bytes, each referenced file's name and bytes (in document order), and the film size."""
    path = Path(path).resolve()
    root = _parse(path)
    _sensors(root, path)
    size = resolution if resolution is not None else xml_resolution(path)
    parts = [b"xml;%d;" % path.stat().st_size, path.read_bytes()]
    for element, attribute, target in _referenced_files(path, root):
        name = element.get(attribute, "").encode("utf-8")
        data = target.read_bytes()
        parts += [b"file;%d;" % len(name), name, b"%d;" % len(data), data]
    parts.append(b"resolution;%d;%d" % (int(size[0]), int(size[1])))
    return b"".join(parts)


def _scene_id(name: str) -> str:
    return "xml-" + (re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "scene")


def _is_scene_file(path: Path) -> bool:
    root = _parse(path)
    return root.tag == "scene" and next(root.iter("sensor"), None) is not None


def xml_corpus(dirs: list[str], resolution: tuple[int, int] | None) -> list[SceneSpec]:
    """One spec per XML scene in each folder: `*.xml` in the folder and in its direct subfolders.

    A file counts as a scene when its root is <scene> and it has a <sensor>; fragments pulled in
    by <include> have none and are skipped. A subfolder holding one scene is named after the folder.
    """
    specs: dict[str, SceneSpec] = {}
    for folder in map(Path, dirs):
        if not folder.is_dir():
            raise SceneError(f"{folder}: scene folder not found")
        found: list[tuple[str, Path]] = [(path.stem, path) for path in sorted(folder.glob("*.xml")) if _is_scene_file(path)]
        for sub in sorted(p for p in folder.iterdir() if p.is_dir()):
            scenes = [path for path in sorted(sub.glob("*.xml")) if _is_scene_file(path)]
            found += [(sub.name if len(scenes) == 1 else f"{sub.name}-{path.stem}", path) for path in scenes]
        if not found:
            raise SceneError(f"{folder}: no Mitsuba scene (an .xml file with a <sensor>) in this folder or its subfolders")
        for name, path in found:
            scene_id = _scene_id(name)
            if scene_id in specs:
                raise SceneError(f"{path}: scene id {scene_id!r} is already taken by {specs[scene_id].xml_path}")
            size = tuple(resolution) if resolution is not None else xml_resolution(path)
            specs[scene_id] = SceneSpec(scene_id, XML_FAMILY, 0, size, str(path.resolve()))
    return list(specs.values())
