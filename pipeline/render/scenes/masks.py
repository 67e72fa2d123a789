"""Seeded single-channel images with hard edges: projector slides (gobos), occluder opacity
(grates, foliage) and height maps for bump and normal mapping.

All are (H, W) float arrays in [0, 1]. What they share is what the procedural families lacked:
detail at the scale of a few pixels *inside* a lit region or on a flat surface, where a denoiser
that learned only smooth irradiance would smear it away.
"""

from __future__ import annotations

import numpy as np

from .textures import value_noise

MASK_SIZE = 128


def _uv(size: int) -> tuple[np.ndarray, np.ndarray]:
    coords = (np.arange(size) + 0.5) / size
    return np.meshgrid(coords, coords, indexing="xy")


def _rotated(rng: np.random.Generator, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    angle = rng.uniform(0.0, np.pi)
    cos, sin = np.cos(angle), np.sin(angle)
    return cos * (u - 0.5) - sin * (v - 0.5), sin * (u - 0.5) + cos * (v - 0.5)


def bars(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    """Parallel bars at a random angle: 3-10 periods across, 30-70 % open."""
    u, v = _rotated(rng, *_uv(size))
    return ((u * rng.uniform(3.0, 10.0)) % 1.0 < rng.uniform(0.3, 0.7)).astype(np.float64)


def grid(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    """A grate: square holes in a lattice of 3-8 cells per side."""
    u, v = _rotated(rng, *_uv(size))
    cells, open_fraction = rng.uniform(3.0, 8.0), rng.uniform(0.5, 0.8)
    return (((u * cells) % 1.0 < open_fraction) & ((v * cells) % 1.0 < open_fraction)).astype(np.float64)


def dots(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    """Round holes on a lattice (a perforated plate, a disco gobo)."""
    u, v = _rotated(rng, *_uv(size))
    cells = rng.uniform(3.0, 9.0)
    fu, fv = (u * cells) % 1.0 - 0.5, (v * cells) % 1.0 - 0.5
    return (fu * fu + fv * fv < rng.uniform(0.08, 0.2)).astype(np.float64)


def foliage(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    """Leaf-like blobs: thresholded fractal noise, 35-65 % open (dappled light under a tree)."""
    field = value_noise(rng, size, octaves=4, base=int(rng.integers(3, 7)))
    return (field > np.quantile(field, rng.uniform(0.35, 0.65))).astype(np.float64)


def spokes(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    """Radial sectors and rings (a window-frame or a fan gobo)."""
    u, v = _uv(size)
    angle, radius = np.arctan2(v - 0.5, u - 0.5), np.hypot(u - 0.5, v - 0.5)
    sectors = (angle * int(rng.integers(3, 9)) / np.pi) % 2.0 < 1.0
    rings = (radius * rng.uniform(4.0, 10.0)) % 1.0 < rng.uniform(0.4, 0.8)
    return (sectors ^ rings).astype(np.float64)


GOBOS = {"bars": bars, "grid": grid, "dots": dots, "foliage": foliage, "spokes": spokes}
GOBO_NAMES = tuple(sorted(GOBOS))


def random_gobo(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    return GOBOS[GOBO_NAMES[int(rng.integers(len(GOBO_NAMES)))]](rng, size)


def tiles(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    """Heights of tiles or bricks with grooves: 1 on a tile, 0 in a groove (rows offset for bricks)."""
    u, v = _uv(size)
    rows, columns = int(rng.integers(3, 9)), int(rng.integers(2, 7))
    shift = 0.5 * (np.floor(v * rows) % 2) if rng.uniform() < 0.5 else 0.0
    groove = rng.uniform(0.05, 0.12)
    return (((u * columns + shift) % 1.0 > groove) & ((v * rows) % 1.0 > groove)).astype(np.float64)


def ripples(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    """Smooth waves (hammered metal, a rippled surface), a sum of a few tileable plane waves."""
    u, v = _uv(size)
    total = np.zeros_like(u)
    for _ in range(3):
        ku, kv = rng.integers(-8, 9, 2)
        total += np.sin(2.0 * np.pi * (ku * u + kv * v) + rng.uniform(0.0, 2.0 * np.pi))
    return (total - total.min()) / (np.ptp(total) + 1e-9)


def rough_noise(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    field = value_noise(rng, size, octaves=5, base=int(rng.integers(4, 9)))
    return (field - field.min()) / (np.ptp(field) + 1e-9)


HEIGHTS = {"tiles": tiles, "ripples": ripples, "noise": rough_noise}
HEIGHT_NAMES = tuple(sorted(HEIGHTS))


def random_height(rng: np.random.Generator, size: int = MASK_SIZE) -> np.ndarray:
    return HEIGHTS[HEIGHT_NAMES[int(rng.integers(len(HEIGHT_NAMES)))]](rng, size)


def normal_map(height: np.ndarray, strength: float) -> np.ndarray:
    """A tangent-space normal map (RGB in [0, 1], Mitsuba's `normalmap` encoding) of a tileable height map."""
    size = height.shape[0]
    d_u = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) * size / 2.0
    d_v = (np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) * size / 2.0
    normal = np.stack([-strength * d_u, -strength * d_v, np.ones_like(height)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return 0.5 * normal + 0.5
