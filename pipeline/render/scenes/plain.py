"""Variant-free scene descriptions and their canonical bytes.

Families build a *plain* description: the `mi.load_dict` dict, except that transforms, images
and meshes are NumPy-backed markers. That keeps generation independent of the Mitsuba variant
(a hash needs no renderer) and lets `canonical_bytes` hash exactly what will be rendered.
Every float is snapped to a binary grid: NumPy's SIMD sin/exp may differ in the last bit
between CPUs, and snapping makes the same seed give the same bytes on any machine.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

GRID = 2.0**-16  # 15 µm for positions in metres, 1.5e-5 for colours and normals


def snap(value: float) -> float:
    """Round a scalar to the shared grid so last-bit platform differences vanish."""
    return float(round(float(value) / GRID) * GRID)


def snap_array(array: np.ndarray, dtype=np.float32) -> np.ndarray:
    return (np.round(np.asarray(array, dtype=np.float64) / GRID) * GRID).astype(dtype)


@dataclass(frozen=True, eq=False)
class Matrix:
    """A 4x4 row-major to_world transform."""

    values: np.ndarray


@dataclass(frozen=True, eq=False)
class Image:
    """An (H, W, 3) linear float32 image, used as a bitmap texture or an environment map."""

    pixels: np.ndarray


@dataclass(frozen=True, eq=False)
class MeshData:
    """A triangle mesh in world space with per-vertex normals and texture coordinates."""

    vertices: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (M, 3) uint32
    normals: np.ndarray  # (N, 3) float32
    texcoords: np.ndarray  # (N, 2) float32


@dataclass(frozen=True, eq=False)
class MeshShape:
    """A procedural mesh with its BSDF (a plain dict), turned into an `mi.Mesh` on load."""

    mesh: MeshData
    bsdf: dict


def canonicalise(node: Any) -> Any:
    """Snap every float in a plain description (scalars and arrays) and fix array dtypes."""
    if isinstance(node, dict):
        return {str(key): canonicalise(value) for key, value in node.items()}
    if isinstance(node, (list, tuple)):
        return [canonicalise(value) for value in node]
    if isinstance(node, bool):
        return node
    if isinstance(node, (int, np.integer)):
        return int(node)
    if isinstance(node, (float, np.floating)):
        return snap(node)
    if isinstance(node, str):
        return node
    if isinstance(node, Matrix):
        return Matrix(snap_array(node.values, np.float64).reshape(4, 4))
    if isinstance(node, Image):
        return Image(np.ascontiguousarray(snap_array(node.pixels)))
    if isinstance(node, MeshData):
        return MeshData(
            vertices=np.ascontiguousarray(snap_array(node.vertices)),
            faces=np.ascontiguousarray(node.faces, dtype=np.uint32),
            normals=np.ascontiguousarray(snap_array(node.normals)),
            texcoords=np.ascontiguousarray(snap_array(node.texcoords)),
        )
    if isinstance(node, MeshShape):
        return MeshShape(canonicalise(node.mesh), canonicalise(node.bsdf))
    raise TypeError(f"plain scene descriptions cannot hold {type(node).__name__}: {node!r}")


def canonical_bytes(node: Any) -> bytes:
    """A byte string that depends only on the description's content (sorted keys, little-endian)."""
    out: list[bytes] = []
    _write(node, out)
    return b"".join(out)


def _write(node: Any, out: list[bytes]) -> None:
    if isinstance(node, dict):
        out.append(b"D%d;" % len(node))
        for key in sorted(node):
            _write(key, out)
            _write(node[key], out)
    elif isinstance(node, list):
        out.append(b"L%d;" % len(node))
        for value in node:
            _write(value, out)
    elif isinstance(node, str):
        data = node.encode("utf-8")
        out.append(b"S%d;" % len(data) + data)
    elif isinstance(node, bool):
        out.append(b"B1;" if node else b"B0;")
    elif isinstance(node, int):
        out.append(b"I%d;" % node)
    elif isinstance(node, float):
        out.append(b"F" + struct.pack("<d", node))
    elif isinstance(node, np.ndarray):
        array = np.ascontiguousarray(node, dtype=node.dtype.newbyteorder("<"))
        out.append(b"A" + array.dtype.str.encode() + repr(array.shape).encode() + b";" + array.tobytes())
    elif isinstance(node, (Matrix, Image, MeshData, MeshShape)):
        out.append(b"M" + type(node).__name__.encode() + b";")
        for field in fields(node):
            _write(getattr(node, field.name), out)
    else:
        raise TypeError(f"cannot serialise {type(node).__name__} in a scene description")
