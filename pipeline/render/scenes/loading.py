"""From a spec to a Mitsuba scene, a load_dict dict, and a content hash.

Procedural specs go through their family's plain description (`plain.py`), which is turned
into Mitsuba objects only here, once a variant is active. XML specs go through `xml_loader`.
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np

from . import xml_loader
from .constructs import CONSTRUCTS
from .families import FAMILIES
from .plain import Image, Matrix, MeshShape, canonical_bytes, canonicalise
from .spec import SceneError, SceneSpec


def plain_description(spec: SceneSpec) -> dict:
    """The canonical, variant-free description of a procedural spec."""
    if spec.is_xml:
        raise SceneError(f"scene {spec.scene_id!r} is an XML scene ({spec.xml_path}); it has no procedural description")
    family = FAMILIES.get(spec.family)
    if family is None:
        raise SceneError(
            f"scene {spec.scene_id!r}: unknown family {spec.family!r}; known: {', '.join(sorted(FAMILIES))}"
        )
    unknown = [name for name in spec.constructs if name not in CONSTRUCTS]
    if unknown:
        raise SceneError(
            f"scene {spec.scene_id!r}: unknown constructs {unknown}; known: {', '.join(sorted(CONSTRUCTS))}"
        )
    return canonicalise(family.build(spec.seed, spec.resolution, spec.constructs))


def _to_mitsuba(node: Any, name: str = "") -> Any:
    import mitsuba as mi

    if isinstance(node, dict):
        return {key: _to_mitsuba(value, key) for key, value in node.items()}
    if isinstance(node, list):
        return [_to_mitsuba(value) for value in node]
    if isinstance(node, Matrix):
        return mi.ScalarTransform4f(node.values.tolist())
    if isinstance(node, Image):
        return mi.Bitmap(np.ascontiguousarray(node.pixels, dtype=np.float32))
    if isinstance(node, MeshShape):
        return _mesh(node, name)
    return node


def _mesh(shape: MeshShape, name: str):
    import mitsuba as mi

    data = shape.mesh
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_to_mitsuba(shape.bsdf))
    mesh = mi.Mesh(
        name, len(data.vertices), len(data.faces), props=props, has_vertex_normals=True, has_vertex_texcoords=True
    )
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(data.vertices.ravel())
    params["faces"] = mi.UInt32(data.faces.ravel())
    params["vertex_normals"] = mi.Float(data.normals.ravel())
    params["vertex_texcoords"] = mi.Float(data.texcoords.ravel())
    params.update()
    mesh.set_id(name)  # without an id Mitsuba names it after its address, which reorders shapes between loads
    return mesh


def scene_description(spec: SceneSpec) -> dict:
    """The `mi.load_dict` dict of a procedural spec (needs an active variant: it holds
    `mi.Mesh`, `mi.Bitmap` and transform objects)."""
    return _to_mitsuba(plain_description(spec))


def load_scene(spec: SceneSpec, spp: int = 1):
    """The Mitsuba scene of any spec, film = hdrfilm with a box filter at spec.resolution; an XML
    scene that takes $spp gets `spp` (pass the spp rendered; the render's own spp rules the sampler).

    Loaded with `optimize=False`: Mitsuba's shape merging orders shapes and emitters by memory
    address, so the same spec would render differently (same statistics, other bits) per load.
    """
    if spec.is_xml:
        return xml_loader.load_xml_scene(spec.xml_path, spec.resolution, spp)
    try:
        return load_description(plain_description(spec))
    except RuntimeError as error:
        raise SceneError(
            f"scene {spec.scene_id!r} ({spec.family}, seed {spec.seed}) failed to load: {error}"
        ) from error


def load_description(plain: dict):
    """The Mitsuba scene of a plain description (`optimize=False`, see `load_scene`)."""
    import mitsuba as mi

    return mi.load_dict(_to_mitsuba(canonicalise(plain)), optimize=False)


def scene_hash(spec: SceneSpec) -> str:
    """sha256 of what will be rendered: the canonical description with all array bytes, or the
    XML bytes plus every file it references plus the film resolution."""
    digest = hashlib.sha256()
    if spec.is_xml:
        digest.update(b"admc-xml-scene-v1;")
        digest.update(xml_loader.xml_content_bytes(spec.xml_path, spec.resolution))
    else:
        digest.update(b"admc-procedural-scene-v1;")
        digest.update(canonical_bytes(plain_description(spec)))
    return digest.hexdigest()
