"""User Mitsuba XML scenes: discovery, loading with our film, and the bytes that identify them.

A user's file may carry any film, reconstruction filter or integrator. We parse it with
ElementTree, inline its <include>d files (published scenes often keep the camera and lights in a
shared include), swap every sensor's film for an `hdrfilm` with a `box` filter (a Gaussian splats
samples across pixels, which denoisers handle badly), rewrite referenced file names to absolute
paths and load the result with `mi.load_string`, passing the parameters `mitsuba -D` would
(SCENE_PARAMETERS). Referenced files are found the way Mitsuba's own parser finds them (its file
resolver, the scene's <path> folders included) and checked up front, so a missing mesh is reported
by name instead of as a parser error deep inside Mitsuba, and the scene hash covers exactly the
files Mitsuba loads.
"""

from __future__ import annotations

import copy
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from .spec import XML_FAMILY, NotAScene, SceneError, SceneSpec

DEFAULT_RESOLUTION = (768, 576)  # Mitsuba's hdrfilm default, used when the XML gives none
SCENE_PARAMETERS = ("spp", "resx", "resy")
"""What published scenes take from `mitsuba -D name=value`: admc passes the spp it renders and the film
size to a scene that uses them (Mitsuba refuses a parameter a scene does not use)."""
_REFERENCE = re.compile(r"\$(\w+)")
_MITSUBA_SOURCE = re.compile(r"\[[\w.]+:\d+\] ")  # where in Mitsuba's C++ an error was raised
_AT_STRING = re.compile(r"At string \(line (\d+), col (\d+)\): ")  # where in the rewritten XML we loaded


def _parse(path: Path) -> ET.Element:
    if not path.is_file():
        raise SceneError(f"{path}: scene file not found")
    try:
        return ET.parse(path).getroot()
    except ET.ParseError as error:
        raise SceneError(f"{path}: malformed XML ({error})") from error


def _defaults(root: ET.Element) -> dict[str, str]:
    """A name's first <default> wins, as in Mitsuba's parser (an including file's, before its includes')."""
    return {d.get("name"): d.get("value", "") for d in reversed(list(root.iter("default"))) if d.get("name")}


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
    """The film size the XML itself asks for (first sensor, includes read), Mitsuba's default if it gives none."""
    path = Path(path)
    root = _expanded(path)
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


@dataclass(frozen=True)
class _Reference:
    element: ET.Element
    attribute: str
    name: str  # as its file writes it, $defaults substituted
    target: Path  # the absolute file (or <path> folder) Mitsuba's resolver finds
    owner: Path  # the XML file that names it


def _references(path: Path, root: ET.Element, trees: dict[Path, ET.Element] | None = None) -> list[_Reference]:
    """Every file and <path> folder the scene references, through includes, found as Mitsuba 3.9's parser does;
    `trees` receives each included file's parsed root, by its absolute path.

    The parser gives each XML file a copy of the global file resolver with the file's folder in
    front; a <path> (relative: found on that search path) goes in front of that. <include> and
    <spectrum filename> resolve while parsing, so they see only the <path>s before them; plugins'
    `filename` strings, an included file's too, resolve afterwards on the scene file's final search path.
    """
    import mitsuba as mi

    strings: list[tuple[ET.Element, str, Path]] = []
    resolver, found = _parsed_references(path, root, mi.file_resolver(), {}, strings, {} if trees is None else trees)
    return found + [
        _Reference(element, "value", name, _resolve(resolver, name, owner), owner) for element, name, owner in strings
    ]


def _parsed_references(
    path: Path, root: ET.Element, outer, inherited: dict[str, str], strings: list, trees: dict[Path, ET.Element]
) -> tuple[object, list[_Reference]]:
    """One file's parse-time references (and its includes'); its `filename` strings go to `strings`.

    Returns the file's search path at its end, with the references in document order.
    """
    import mitsuba as mi

    resolver = mi.FileResolver(outer)
    resolver.prepend(str(path.parent))
    defaults = {**_defaults(root), **inherited}  # a name's first <default> wins: the including file's
    top_level = {id(child) for child in root}
    found = []
    for element in root.iter():
        if element.tag == "path" and id(element) in top_level:
            name = _substitute(element.get("value", ""), defaults, path)
            folder = Path(name) if Path(name).is_absolute() else Path(str(resolver.resolve(name)))
            if not folder.is_dir():
                raise SceneError(f"{path}: <path> folder {name!r} not found (looked in {_search_list(resolver)})")
            folder = folder.resolve()
            resolver.prepend(str(folder))
            found.append(_Reference(element, "value", name, folder, path))
        elif element.tag == "string" and element.get("name") == "filename":
            strings.append((element, _substitute(element.get("value", ""), defaults, path), path))
        elif "filename" in element.attrib:  # <include>, <spectrum>
            name = _substitute(element.get("filename", ""), defaults, path)
            reference = _Reference(element, "filename", name, _resolve(resolver, name, path), path)
            found.append(reference)
            if element.tag == "include" and reference.target not in trees:
                trees[reference.target] = _parse(reference.target)
                found += _parsed_references(
                    reference.target, trees[reference.target], resolver, defaults, strings, trees
                )[1]
    return resolver, found


def _resolve(resolver, name: str, owner: Path) -> Path:
    target = Path(str(resolver.resolve(name)))
    if not target.is_file():
        raise SceneError(f"{owner}: referenced file {name!r} not found (looked in {_search_list(resolver)})")
    return target.resolve()


def _search_list(resolver) -> str:
    """The folders the scene put on the search path (Mitsuba's own defaults after them are left out)."""
    import mitsuba as mi

    folders = [str(folder) for folder in resolver]
    return ", ".join(folders[: len(folders) - len(list(mi.file_resolver()))])


def _hdr_film(width: int, height: int) -> ET.Element:
    film = ET.Element("film", type="hdrfilm")
    ET.SubElement(film, "integer", name="width", value=str(width))
    ET.SubElement(film, "integer", name="height", value=str(height))
    ET.SubElement(film, "string", name="pixel_format", value="rgb")
    ET.SubElement(film, "rfilter", type="box")
    return film


def _expanded(path: Path, trees: dict[Path, ET.Element] | None = None) -> ET.Element:
    """The scene as Mitsuba reads it, as one tree: each <include> replaced by the included file's
    contents, and every file name absolute (found where Mitsuba's parser finds it). `trees` receives
    the included files' own trees, by absolute path."""
    root = _parse(path)
    trees = {} if trees is None else trees
    for reference in _references(path, root, trees):
        reference.element.set(reference.attribute, str(reference.target))
    _inline(root, trees, [path.resolve()])
    return root


def _inline(element: ET.Element, trees: dict[Path, ET.Element], chain: list[Path]) -> None:
    for index in reversed(range(len(element))):
        child = element[index]
        if child.tag != "include":
            _inline(child, trees, chain)
            continue
        target = Path(child.get("filename"))
        if target in chain:
            raise SceneError(f"{chain[0]}: its includes form a cycle ({' -> '.join(p.name for p in chain + [target])})")
        included = copy.deepcopy(trees[target])  # a file included twice is inlined twice
        _inline(included, trees, chain + [target])
        element[index : index + 1] = list(included)


def _check_parameters(path: Path, root: ET.Element) -> None:
    """Every $name the expanded scene uses has a <default> or is one admc passes (SCENE_PARAMETERS)."""
    defined = set(_defaults(root)) | set(SCENE_PARAMETERS)
    for element in root.iter():
        for value in element.attrib.values():
            for name in _REFERENCE.findall(value):
                if name not in defined:
                    raise SceneError(
                        f"{path}: ${name} is used but has no <default> (admc passes only "
                        f"{', '.join('$' + p for p in SCENE_PARAMETERS)}, as `mitsuba -D` would)"
                    )


def _parameters(text: str, resolution: tuple[int, int], spp: int) -> dict[str, str]:
    """The SCENE_PARAMETERS the scene uses, with the values of this render."""
    values = {"spp": spp, "resx": resolution[0], "resy": resolution[1]}
    return {name: str(values[name]) for name in sorted(set(_REFERENCE.findall(text)) & set(SCENE_PARAMETERS))}


def prepared_xml(path: str | Path, resolution: tuple[int, int] | None) -> str:
    """The scene's XML, includes inlined, with our film in every sensor and absolute file names."""
    path = Path(path)
    root = _expanded(path)
    sensors = _sensors(root, path)
    width, height = resolution if resolution is not None else xml_resolution(path)
    for sensor in sensors:
        for film in sensor.findall("film"):
            sensor.remove(film)
        sensor.append(_hdr_film(int(width), int(height)))
    return ET.tostring(root, encoding="unicode")


def load_xml_scene(path: str | Path, resolution: tuple[int, int] | None = None, spp: int = 1):
    """Load a user scene with an hdrfilm + box filter at `resolution` (None keeps the XML's); a scene
    that takes $spp, $resx or $resy gets `spp` and the film size (the render's own spp overrides the
    scene's sampler anyway).

    File names are absolute; the scene's folder is put on Mitsuba's (process-wide) file resolver for
    the duration of the load all the same, as `mi.load_file` would.
    """
    import mitsuba as mi

    path = Path(path).resolve()
    size = resolution if resolution is not None else xml_resolution(path)
    text = prepared_xml(path, size)
    saved = mi.FileResolver(mi.file_resolver())
    mi.file_resolver().prepend(str(path.parent))
    try:  # merging reorders shapes per load (see loading.py)
        return mi.load_string(text, optimize=False, **_parameters(text, size, spp))
    except RuntimeError as error:
        problem = _AT_STRING.sub(lambda match: _element_at(text, match), _MITSUBA_SOURCE.sub("", str(error)))
        raise SceneError(f"{path}: Mitsuba could not load the scene: {problem}") from error
    finally:
        mi.set_file_resolver(saved)


def _element_at(text: str, match: re.Match) -> str:
    """Mitsuba's line and column point into our rewritten XML, which the user never sees: name the
    element there and the files it names instead."""
    data = text.encode("utf-8")
    line, column = int(match[1]), int(match[2])
    offset = sum(len(row) + 1 for row in data.split(b"\n")[: line - 1]) + column - 1  # at the tag's name
    index = len(re.findall(rb"<(?![/!?])", data[:offset])) - 1  # elements start in document order
    elements = list(ET.fromstring(text).iter())
    if not 0 <= index < len(elements):
        return ""
    element = elements[index]
    files = [e.get("value", "") for e in element.iter() if e.tag == "string" and e.get("name") == "filename"]
    files += [e.get("filename", "") for e in element.iter() if "filename" in e.attrib]
    return f"<{element.tag}> naming {', '.join(files)}: " if files else ""  # Mitsuba's message names the plugin


def xml_content_bytes(path: str | Path, resolution: tuple[int, int] | None) -> bytes:
    """The XML bytes, the name and bytes of each file Mitsuba will load for it, and the film size."""
    path = Path(path).resolve()
    root = _parse(path)
    size = resolution if resolution is not None else xml_resolution(path)
    parts = [b"xml;%d;" % path.stat().st_size, path.read_bytes()]
    for reference in _references(path, root):
        if reference.element.tag == "path":
            continue  # a search folder: the files found through it count, not the folder
        name = reference.name.encode("utf-8")
        data = reference.target.read_bytes()
        parts += [b"file;%d;" % len(name), name, b"%d;" % len(data), data]
    parts.append(b"resolution;%d;%d" % (int(size[0]), int(size[1])))
    return b"".join(parts)


def _scene_id(name: str) -> str:
    return "xml-" + (re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "scene")


def xml_corpus(
    dirs: list[str], resolution: tuple[int, int] | None, left_out: list[SceneError] | None = None
) -> list[SceneSpec]:
    """One spec per XML scene in each folder: `*.xml` in the folder and in its direct subfolders.

    What is a scene is decided as Mitsuba reads the file, includes inlined: a <scene> with a <sensor>,
    in it or in a file it includes. A file another file of the folder includes is a part of those
    scenes, not a scene of its own; it and the files without a camera are left out as NotAScene. A
    subfolder holding one scene is named after the folder. Each scene is checked as far as its
    render would check it (XML, film size, every referenced file, its $parameters) and must hold an
    emitter: an unlit scene renders black, training data of nothing. A file that fails raises its
    SceneError or, when `left_out` is a list, is left out and its error appended there (so are the
    NotAScene files, which are otherwise just skipped): one broken file then does not hold up the
    other scenes.
    """
    specs: dict[str, SceneSpec] = {}
    problems: list[SceneError] = []
    for folder in map(Path, dirs):
        if not folder.is_dir():
            raise SceneError(f"{folder}: scene folder not found")
        found, broken = _scene_files(folder)
        if not found and not any(not isinstance(error, NotAScene) for error in broken):
            raise SceneError(
                f"{folder}: no Mitsuba scene (an .xml file with a <sensor>) in this folder or its "
                f"subfolders{''.join('; ' + str(error) for error in broken)}"
            )
        problems += broken
        for name, path in found:
            scene_id = _scene_id(name)
            if scene_id in specs:
                raise SceneError(f"{path}: scene id {scene_id!r} is already taken by {specs[scene_id].xml_path}")
            try:
                specs[scene_id] = _checked_spec(scene_id, path, resolution)
            except SceneError as error:
                problems.append(error)
    if left_out is not None:
        left_out.extend(problems)
    else:
        errors = [error for error in problems if not isinstance(error, NotAScene)]
        if errors:
            raise errors[0]
    return list(specs.values())


def _scene_files(folder: Path) -> tuple[list[tuple[str, Path]], list[SceneError]]:
    """(name, path) of the scenes in a folder and its direct subfolders, and the files left out:
    those that do not load (SceneError) and those that are no scene of their own (NotAScene).

    A part is read as the files including it read it (its file names on their search path), so on
    its own it may not load: that is no error of a part, nor of a file that could never be a scene
    (neither a <sensor> nor an <include> in it)."""
    left_out: list[SceneError] = []
    candidates: dict[Path, ET.Element | SceneError] = {}  # the <scene> files, expanded or why not
    includers: dict[Path, list[Path]] = {}  # an included file -> the files including it
    places = [folder] + sorted(p for p in folder.iterdir() if p.is_dir())
    for path in (path for where in places for path in sorted(where.glob("*.xml"))):
        try:
            root = _parse(path)
        except SceneError as error:
            left_out.append(error)
            continue
        if root.tag != "scene":
            left_out.append(NotAScene(f"{path}: skipped, not a Mitsuba scene (its root element is <{root.tag}>)"))
            continue
        trees: dict[Path, ET.Element] = {}
        try:
            candidates[path] = _expanded(path, trees)
        except SceneError as error:
            whole = next(root.iter("sensor"), None) is not None or next(root.iter("include"), None) is not None
            candidates[path] = error if whole else root
            continue
        for included in trees:
            includers.setdefault(included, []).append(path)
    scenes: dict[Path, list[Path]] = {where: [] for where in places}
    for path, root in candidates.items():
        if path.resolve() in includers:
            by = includers[path.resolve()]
            names = ", ".join(p.name for p in by[:3]) + (f" and {len(by) - 3} more" if len(by) > 3 else "")
            left_out.append(
                NotAScene(f"{path}: skipped, a part of other scenes, not a scene of its own (included by {names})")
            )
        elif isinstance(root, SceneError):
            left_out.append(root)
        elif next(root.iter("sensor"), None) is None:
            left_out.append(NotAScene(f"{path}: skipped, no <sensor> (camera) in it or in the files it includes"))
        else:
            scenes[path.parent].append(path)
    found = [(path.stem, path) for path in scenes[folder]]
    for sub in places[1:]:
        found += [(sub.name if len(scenes[sub]) == 1 else f"{sub.name}-{path.stem}", path) for path in scenes[sub]]
    return found, left_out


def _checked_spec(scene_id: str, path: Path, resolution: tuple[int, int] | None) -> SceneSpec:
    """A scene file's spec, once its film size reads, every file it references is found, every
    $parameter it uses is defined, and it holds an emitter."""
    size = tuple(resolution) if resolution is not None else xml_resolution(path)
    root = _expanded(path)
    _check_parameters(path, root)
    if next(root.iter("emitter"), None) is None:
        raise SceneError(
            f"{path}: no <emitter> (no light, no environment) in it or in the files it includes: "
            "it would render black; add a light or move the file out of the scene folder"
        )
    return SceneSpec(scene_id, XML_FAMILY, 0, size, str(path.resolve()))
