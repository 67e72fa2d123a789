"""Procedural texture images and meshes that the domain scenes reference as files.

Textures are linear RGB EXRs (Mitsuba's `bitmap` reads EXR as linear), albedos kept within
[0.03, 0.85]. Meshes are Wavefront OBJ with per-vertex normals and texture coordinates. Everything is
drawn from a seeded generator, so the same seed writes the same bytes on any machine.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import OpenEXR

SIZE = 256


def _uv(size: int = SIZE) -> tuple[np.ndarray, np.ndarray]:
    coords = (np.arange(size) + 0.5) / size
    return np.meshgrid(coords, coords, indexing="xy")


def noise(rng: np.random.Generator, size: int = SIZE, octaves: int = 4, base: int = 4) -> np.ndarray:
    """Tileable fractal value noise in [0, 1] (bilinear lattice, smooth-stepped)."""
    total, weights = np.zeros((size, size)), 0.0
    for octave in range(octaves):
        cells = base * 2**octave
        lattice = rng.uniform(0.0, 1.0, (cells, cells))
        pos = (np.arange(size) + 0.5) * cells / size - 0.5
        i0 = np.floor(pos).astype(int)
        t = pos - i0
        t = t * t * (3 - 2 * t)
        a, b = i0 % cells, (i0 + 1) % cells
        rows = lattice[a][:, a] * (1 - t)[None, :] + lattice[a][:, b] * t[None, :]
        rows2 = lattice[b][:, a] * (1 - t)[None, :] + lattice[b][:, b] * t[None, :]
        layer = rows * (1 - t)[:, None] + rows2 * t[:, None]
        weight = 0.5**octave
        total, weights = total + weight * layer, weights + weight
    return total / weights


def _mix(mask: np.ndarray, low, high) -> np.ndarray:
    mask = np.clip(mask, 0.0, 1.0)[..., None]
    return (1.0 - mask) * np.asarray(low, float) + mask * np.asarray(high, float)


def wood_planks(rng: np.random.Generator, tone, planks: int = 4) -> np.ndarray:
    """Floor boards running along u: per-board tone, grain lines bent by noise, dark seams."""
    u, v = _uv()
    grain_noise = noise(rng, octaves=3, base=2)
    board = np.floor(v * planks).astype(int)
    shade = rng.uniform(0.75, 1.2, planks)[board]
    offset = rng.uniform(0, 1, planks)[board]
    grain = 0.5 + 0.5 * np.sin(2 * math.pi * (v * planks * 6 + 3 * grain_noise + offset * 7))
    base = np.asarray(tone, float)
    image = _mix(grain**3, base, base * 0.6) * shade[..., None]
    ends = np.abs(((u + offset * 0.5) % 0.5) - 0.25) < 0.004  # board ends, staggered per board
    seam = (np.abs(v * planks - np.round(v * planks)) < 0.03) | ends
    image[seam] *= 0.35
    return np.clip(image, 0.03, 0.85)


def fabric(rng: np.random.Generator, colour) -> np.ndarray:
    """A woven cloth: fine warp and weft threads with slubs."""
    u, v = _uv()
    threads = 48
    warp = 0.5 + 0.5 * np.sin(2 * math.pi * u * threads)
    weft = 0.5 + 0.5 * np.sin(2 * math.pi * v * threads)
    over = (np.floor(u * threads) + np.floor(v * threads)) % 2
    weave = np.where(over > 0, warp, weft)
    slub = noise(rng, octaves=3, base=8)
    base = np.asarray(colour, float)
    return np.clip(base * (0.7 + 0.3 * weave[..., None]) * (0.85 + 0.3 * slub[..., None]), 0.03, 0.85)


def bricks(rng: np.random.Generator, colour, rows: int = 8, mortar=(0.55, 0.53, 0.5)) -> np.ndarray:
    """Running-bond bricks (u: 4 bricks per row), per-brick tone, mortar joints."""
    u, v = _uv()
    row = np.floor(v * rows)
    shifted = u * 4 + 0.5 * (row % 2)
    col = np.floor(shifted)
    ids = (row * 17 + col * 31).astype(int) % 97
    tones = rng.uniform(0.7, 1.25, 97)[ids]
    grit = noise(rng, octaves=4, base=8)
    brick = np.asarray(colour, float) * tones[..., None] * (0.8 + 0.4 * grit[..., None])
    joint = (np.abs(v * rows - np.round(v * rows)) < 0.07) | (np.abs(shifted - np.round(shifted)) < 0.035)
    brick[joint] = np.asarray(mortar) * (0.9 + 0.2 * grit[joint][:, None])
    return np.clip(brick, 0.03, 0.85)


def tiles(rng: np.random.Generator, colour, count: int = 4, grout=(0.6, 0.6, 0.58)) -> np.ndarray:
    """Square tiles or paving stones with grout lines and per-tile tone."""
    u, v = _uv()
    i, j = np.floor(u * count), np.floor(v * count)
    tones = rng.uniform(0.8, 1.15, (count, count))[j.astype(int) % count, i.astype(int) % count]
    speck = noise(rng, octaves=4, base=16)
    image = np.asarray(colour, float) * tones[..., None] * (0.85 + 0.3 * speck[..., None])
    line = (np.abs(u * count - np.round(u * count)) < 0.05) | (np.abs(v * count - np.round(v * count)) < 0.05)
    image[line] = grout
    return np.clip(image, 0.03, 0.85)


def roof_tiles(rng: np.random.Generator, colour, rows: int = 10) -> np.ndarray:
    """Overlapping rows of rounded tiles, darker at each row's lower edge."""
    u, v = _uv()
    row = np.floor(v * rows)
    local = v * rows - row
    across = (u * 8 + 0.5 * (row % 2)) % 1.0
    edge = local - 0.25 * np.sqrt(np.clip(1 - (2 * across - 1) ** 2, 0, 1))
    shade = 0.55 + 0.45 * np.clip(edge * 2, 0, 1)
    tones = rng.uniform(0.8, 1.2, 64)[(row * 7 + np.floor(u * 8)).astype(int) % 64]
    return np.clip(np.asarray(colour, float) * (shade * tones)[..., None], 0.03, 0.85)


def grass(rng: np.random.Generator) -> np.ndarray:
    """Lawn: patchy greens with fine blades (high-frequency noise) and a few dry spots."""
    coarse, fine = noise(rng, octaves=3, base=4), noise(rng, octaves=2, base=64)
    green, dry = np.array([0.08, 0.22, 0.04]), np.array([0.28, 0.27, 0.1])
    image = _mix(np.clip((coarse - 0.55) * 4, 0, 1), green, dry)
    return np.clip(image * (0.6 + 0.8 * fine[..., None]), 0.03, 0.85)


def leaves(rng: np.random.Generator) -> np.ndarray:
    """Foliage: clumps of leaves, dark gaps between them."""
    clumps, fine = noise(rng, octaves=4, base=8), noise(rng, octaves=2, base=32)
    image = _mix(clumps, [0.02, 0.06, 0.02], [0.12, 0.3, 0.06])
    return np.clip(image * (0.7 + 0.6 * fine[..., None]), 0.03, 0.85)


def marble(rng: np.random.Generator, colour=(0.8, 0.78, 0.74)) -> np.ndarray:
    """Veined stone: thin dark veins along a turbulent sine."""
    u, v = _uv()
    turbulence = noise(rng, octaves=5, base=3)
    veins = np.abs(np.sin(2 * math.pi * (u * 2 + v + 4 * turbulence)))
    return np.clip(_mix(veins**0.2, np.asarray(colour) * 0.35, colour), 0.03, 0.85)


def wallpaper(rng: np.random.Generator, colour, accent) -> np.ndarray:
    """Stripes with a row of dots between them: a repeating print with sharp edges."""
    u, v = _uv()
    stripes = (u * 8) % 1.0 < 0.18
    dots = np.hypot((u * 8) % 1.0 - 0.6, (v * 8) % 1.0 - 0.5) < 0.12
    image = np.tile(np.asarray(colour, float), (SIZE, SIZE, 1))
    image[stripes | dots] = accent
    return np.clip(image, 0.03, 0.85)


def painting(rng: np.random.Generator) -> np.ndarray:
    """An abstract canvas: a few saturated colour fields over noise."""
    fields = [noise(rng, octaves=3, base=2) for _ in range(3)]
    image = np.stack(fields, -1) ** 1.5
    return np.clip(image * rng.uniform(0.6, 1.0, 3), 0.03, 0.85)


def write_texture(path: Path, image: np.ndarray) -> str:
    """A float16 RGB EXR; returns the file's name (scenes reference it relative to themselves)."""
    channels = {name: np.ascontiguousarray(image[..., i].astype(np.float16)) for i, name in enumerate("RGB")}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, channels).write(str(path))
    return path.name


def lathe(radii, height: float, segments: int = 48) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A closed solid of revolution about +y, base at the origin: (vertices, normals, uvs, faces)."""
    radii = np.asarray(radii, float)
    rings = len(radii)
    heights = np.linspace(0.0, height, rings)
    tangent = np.stack([np.gradient(radii), np.gradient(heights)], 1)
    normal2 = np.stack([tangent[:, 1], -tangent[:, 0]], 1)
    normal2 /= np.linalg.norm(normal2, axis=1, keepdims=True)
    phi = np.linspace(0.0, 2 * math.pi, segments + 1)
    cos, sin = np.cos(phi)[None], np.sin(phi)[None]
    verts = np.stack([radii[:, None] * cos, np.repeat(heights[:, None], segments + 1, 1), radii[:, None] * sin], -1)
    norms = np.stack([normal2[:, :1] * cos, np.repeat(normal2[:, 1:], segments + 1, 1), normal2[:, :1] * sin], -1)
    uu, vv = np.meshgrid(phi / (2 * math.pi), heights / height)
    vertices, normals, uvs = [verts.reshape(-1, 3)], [norms.reshape(-1, 3)], [np.stack([uu, vv], -1).reshape(-1, 2)]
    r, c = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = (r * (segments + 1) + c).ravel()
    faces = [np.stack([a, a + segments + 1, a + 1], 1), np.stack([a + 1, a + segments + 1, a + segments + 2], 1)]
    count = rings * (segments + 1)
    for ring, up in ((0, -1.0), (rings - 1, 1.0)):  # flat caps with their own vertices
        rim = verts[ring, :segments]
        vertices += [verts[ring, :1] * [0, 1, 0], rim]
        normals.append(np.tile([0.0, up, 0.0], (segments + 1, 1)))
        uvs.append(np.full((segments + 1, 2), 0.5))
        centre, ring_idx = count, count + 1 + np.arange(segments)
        nxt = count + 1 + (np.arange(segments) + 1) % segments
        fan = np.stack([np.full(segments, centre), ring_idx, nxt], 1)
        faces.append(fan if up < 0 else fan[:, [0, 2, 1]])
        count += segments + 1
    return np.concatenate(vertices), np.concatenate(normals), np.concatenate(uvs), np.concatenate(faces)


def cove(radius: float, width: float, segments: int = 24) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The quarter cylinder of a paper sweep, facing its axis: from the floor (y = -radius, z = 0) curving
    up to the wall (z = -radius, y = 0), `width` along x, centred on the origin."""
    theta = np.linspace(0.0, math.pi / 2, segments + 1)
    y, z = -radius * np.cos(theta), -radius * np.sin(theta)
    inward = np.stack([np.zeros_like(theta), np.cos(theta), np.sin(theta)], 1)
    vertices = np.concatenate([np.stack([np.full_like(theta, x), y, z], 1) for x in (-width / 2, width / 2)])
    normals = np.concatenate([inward, inward])
    uvs = np.concatenate([np.stack([np.full_like(theta, u), theta / (math.pi / 2)], 1) for u in (0.0, 1.0)])
    a = np.arange(segments)
    b = a + segments + 1
    faces = np.concatenate([np.stack([a, a + 1, b], 1), np.stack([a + 1, b + 1, b], 1)])
    return vertices, normals, uvs, faces


def prism(profile: np.ndarray, depth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A convex polygon in the xy plane (counter-clockwise) extruded along z from -depth/2 to depth/2,
    with flat-shaded faces: a gable end, a roof ridge, a ramp."""
    profile = np.asarray(profile, float)
    n = len(profile)
    vertices, normals, uvs, faces = [], [], [], []

    def quad_or_poly(points, normal):
        start = sum(len(v) for v in vertices)
        vertices.append(points)
        normals.append(np.tile(normal, (len(points), 1)))
        span = points.max(0) - points.min(0)
        axes = [i for i in range(3) if abs(normal[i]) < 0.9][:2]
        uvs.append((points[:, axes] - points.min(0)[axes]) / np.maximum(span[axes], 1e-6))
        faces.extend([start, start + k, start + k + 1] for k in range(1, len(points) - 1))

    for z, sign in ((depth / 2, 1.0), (-depth / 2, -1.0)):
        cap = np.column_stack([profile, np.full(n, z)])
        quad_or_poly(cap if sign > 0 else cap[::-1], np.array([0, 0, sign]))
    for k in range(n):
        p, q = profile[k], profile[(k + 1) % n]
        edge = q - p
        normal = np.array([edge[1], -edge[0], 0.0]) / np.linalg.norm(edge)
        quad_or_poly(np.array([[*p, depth / 2], [*p, -depth / 2], [*q, -depth / 2], [*q, depth / 2]]), normal)
    return np.concatenate(vertices), np.concatenate(normals), np.concatenate(uvs), np.array(faces)


def write_obj(path: Path, mesh: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> str:
    """A Wavefront OBJ with v, vn, vt per vertex; returns the file's name."""
    vertices, normals, uvs, faces = mesh
    lines = [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in vertices]
    lines += [f"vn {x:.5f} {y:.5f} {z:.5f}" for x, y, z in normals]
    lines += [f"vt {u:.5f} {v:.5f}" for u, v in uvs]
    lines += ["f " + " ".join(f"{i + 1}/{i + 1}/{i + 1}" for i in face) for face in faces]
    path.write_text("\n".join(lines) + "\n")
    return path.name
