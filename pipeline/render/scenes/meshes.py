"""Procedural triangle meshes with smooth vertex normals, a few thousand triangles each.

Normals are analytic (profile derivative, displacement gradient, height gradient) rather than
averaged from faces, so texture seams never show as shading seams.
"""

from __future__ import annotations

import numpy as np

from .geometry import rotate_y_points
from .plain import MeshData


def _unit_rows(vectors: np.ndarray) -> np.ndarray:
    return vectors / np.sqrt(np.sum(vectors * vectors, axis=1, keepdims=True))


def _grid_faces(rows: int, cols: int, offset: int = 0) -> np.ndarray:
    """Two counter-clockwise triangles per cell of a (rows x cols) vertex grid stored row-major."""
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
    a = (r * cols + c).ravel() + offset
    b, d = a + 1, a + cols
    return np.concatenate([np.stack([a, d, b], 1), np.stack([b, d, d + 1], 1)]).astype(np.uint32)


def _placed(vertices, normals, texcoords, faces, center, yaw: float) -> MeshData:
    return MeshData(
        vertices=rotate_y_points(vertices, yaw) + np.asarray(center, dtype=np.float64),
        faces=faces,
        normals=_unit_rows(rotate_y_points(normals, yaw)),
        texcoords=texcoords,
    )


def lathe(radii: np.ndarray, height: float, center, segments: int = 32) -> MeshData:
    """A closed solid of revolution (a vase): `radii` sampled bottom to top, flat caps at both ends.

    Closed so it also works as glass. Profile normals are the 2-D perpendicular of the profile's
    tangent, revolved; the caps have their own vertices so their normals stay flat.
    """
    radii = np.asarray(radii, dtype=np.float64)
    rings = len(radii)
    heights = np.linspace(0.0, height, rings)
    d_radius, d_height = np.gradient(radii), np.gradient(heights)
    profile_normal = np.stack([d_height, -d_radius], 1)
    profile_normal /= np.sqrt(np.sum(profile_normal**2, axis=1, keepdims=True))

    phi = np.linspace(0.0, 2.0 * np.pi, segments + 1)  # the seam vertex is duplicated for texcoords
    sin, cos = np.sin(phi)[None, :], np.cos(phi)[None, :]
    body_vertices = np.stack(
        [radii[:, None] * cos, np.repeat(heights[:, None], segments + 1, 1), radii[:, None] * sin], -1
    )
    body_normals = np.stack(
        [profile_normal[:, :1] * cos, np.repeat(profile_normal[:, 1:], segments + 1, 1), profile_normal[:, :1] * sin],
        -1,
    )
    u, v = np.meshgrid(phi / (2.0 * np.pi), heights / height)
    body_uv = np.stack([u, v], -1)
    vertices, normals, texcoords = (
        [body_vertices.reshape(-1, 3)],
        [body_normals.reshape(-1, 3)],
        [body_uv.reshape(-1, 2)],
    )
    faces = [_grid_faces(rings, segments + 1)]

    count = rings * (segments + 1)
    for ring, y, up in ((0, 0.0, -1.0), (rings - 1, height, 1.0)):
        rim = body_vertices[ring, :segments]
        center_index = count
        vertices += [np.array([[0.0, y, 0.0]]), rim]
        normals.append(np.tile([0.0, up, 0.0], (segments + 1, 1)))
        texcoords.append(
            np.concatenate([[[0.5, 0.5]], 0.5 + 0.5 * np.stack([cos[0, :segments], sin[0, :segments]], 1)])
        )
        rim_index = center_index + 1 + np.arange(segments)
        nxt = center_index + 1 + (np.arange(segments) + 1) % segments
        center_col = np.full(segments, center_index)
        fan = np.stack([center_col, nxt, rim_index], 1) if up > 0 else np.stack([center_col, rim_index, nxt], 1)
        faces.append(fan.astype(np.uint32))
        count += segments + 1
    return _placed(
        np.concatenate(vertices), np.concatenate(normals), np.concatenate(texcoords), np.concatenate(faces), center, 0.0
    )


def bumpy_sphere(
    rng: np.random.Generator,
    radius: float,
    center,
    bumpiness: float = 0.08,
    rings: int = 20,
    segments: int = 40,
    waves: int = 5,
) -> MeshData:
    """A sphere displaced by a sum of random plane waves: r(d) = R (1 + eps * g(d)).

    The normal is d minus the tangential part of grad r / r, exact for this displacement.
    """
    frequencies = rng.normal(size=(waves, 3)) * 2.5
    phases = rng.uniform(0.0, 2.0 * np.pi, waves)
    amplitudes = rng.uniform(0.5, 1.0, waves) / waves

    theta = np.linspace(0.0, np.pi, rings + 1)
    phi = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    direction = np.stack([np.sin(t) * np.cos(p), np.cos(t), np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
    argument = direction @ frequencies.T + phases
    g = np.sin(argument) @ amplitudes
    grad_g = (np.cos(argument) * amplitudes) @ frequencies
    r = radius * (1.0 + bumpiness * g)
    grad_r = radius * bumpiness * grad_g
    tangential = grad_r - np.sum(grad_r * direction, axis=1, keepdims=True) * direction
    normals = _unit_rows(direction - tangential / r[:, None])
    texcoords = np.stack([p / (2.0 * np.pi), 1.0 - t / np.pi], -1).reshape(-1, 2)
    faces = _grid_faces(rings + 1, segments + 1)[:, [0, 2, 1]]  # wind so geometric normals face out
    # Pole rows collapse to a point; drop the degenerate triangles there.
    positions = direction * r[:, None]
    areas = np.linalg.norm(
        np.cross(positions[faces[:, 1]] - positions[faces[:, 0]], positions[faces[:, 2]] - positions[faces[:, 0]]),
        axis=1,
    )
    keep = areas > 1e-12
    return _placed(positions, normals, texcoords, faces[keep], center, 0.0)


def heightfield(
    rng: np.random.Generator,
    size: tuple[float, float],
    amplitude: float,
    center,
    yaw: float = 0.0,
    resolution: int = 24,
    waves: int = 6,
) -> MeshData:
    """A rectangular sheet (a rug, a rippled plate) with height h(x, z) = amplitude * sum of waves."""
    half_x, half_z = size[0] / 2.0, size[1] / 2.0
    x, z = np.meshgrid(
        np.linspace(-half_x, half_x, resolution), np.linspace(-half_z, half_z, resolution), indexing="ij"
    )
    directions = rng.normal(size=(waves, 2)) * (6.0 / max(size))
    phases = rng.uniform(0.0, 2.0 * np.pi, waves)
    weights = rng.uniform(0.5, 1.0, waves) / waves
    argument = x[..., None] * directions[:, 0] + z[..., None] * directions[:, 1] + phases
    h = amplitude * (np.sin(argument) @ weights)
    dh = amplitude * (np.cos(argument) * weights)
    dh_dx, dh_dz = dh @ directions[:, 0], dh @ directions[:, 1]
    vertices = np.stack([x, h, z], -1).reshape(-1, 3)
    normals = _unit_rows(np.stack([-dh_dx, np.ones_like(h), -dh_dz], -1).reshape(-1, 3))
    texcoords = np.stack([(x + half_x) / (2 * half_x), (z + half_z) / (2 * half_z)], -1).reshape(-1, 2)
    faces = _grid_faces(resolution, resolution)[:, [0, 2, 1]]  # wind so geometric normals face +Y
    return _placed(vertices, normals, texcoords, faces, center, yaw)


def ground_quad(half_size: float, repeats: float) -> MeshData:
    """A square at y = 0 facing +Y whose texture coordinates tile `repeats` times per side."""
    corners = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [1.0, 0.0, 1.0], [-1.0, 0.0, 1.0]]) * half_size
    texcoords = (corners[:, [0, 2]] / (2 * half_size) + 0.5) * repeats
    faces = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32)
    return MeshData(corners, faces, np.tile([0.0, 1.0, 0.0], (4, 1)), texcoords)
