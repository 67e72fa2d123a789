"""Procedural images from a seeded generator: albedo textures and a sky environment map.

All images are linear RGB float32 (H, W, 3). Albedos stay within [0.03, 0.85] so no surface
reflects more light than is physically plausible.
"""

from __future__ import annotations

import colorsys

import numpy as np

from .plain import Image

TEXTURE_SIZE = 128
SKY_SIZE = (64, 128)  # (height, width) of the lat-long environment map


def random_colour(rng: np.random.Generator, saturation=(0.1, 0.7), value=(0.3, 0.85)) -> list[float]:
    """A linear RGB albedo with a random hue, drawn in HSV (pure arithmetic, so portable)."""
    hue, sat, val = rng.uniform(0.0, 1.0), rng.uniform(*saturation), rng.uniform(*value)
    return [float(c) for c in colorsys.hsv_to_rgb(hue, sat, val)]


def _two_tone(mask: np.ndarray, low, high) -> np.ndarray:
    mask = mask[..., None]
    return np.clip((1.0 - mask) * np.asarray(low) + mask * np.asarray(high), 0.03, 0.85)


def _uv(size: int) -> tuple[np.ndarray, np.ndarray]:
    coords = (np.arange(size) + 0.5) / size
    return np.meshgrid(coords, coords, indexing="xy")


def value_noise(rng: np.random.Generator, size: int = TEXTURE_SIZE, octaves: int = 4, base: int = 4) -> np.ndarray:
    """Tileable fractal value noise in [0, 1]: smooth-stepped lattice values, summed over octaves."""
    total, weight_sum = np.zeros((size, size)), 0.0
    for octave in range(octaves):
        cells = base * 2**octave
        lattice = rng.uniform(0.0, 1.0, (cells, cells))
        position = (np.arange(size) + 0.5) * cells / size
        index = np.floor(position).astype(int)
        fraction = position - index
        smooth = fraction * fraction * (3.0 - 2.0 * fraction)
        i0, i1 = index % cells, (index + 1) % cells
        rows = lattice[i0][:, i0] * (1 - smooth)[None, :] + lattice[i0][:, i1] * smooth[None, :]
        rows_next = lattice[i1][:, i0] * (1 - smooth)[None, :] + lattice[i1][:, i1] * smooth[None, :]
        layer = rows * (1 - smooth)[:, None] + rows_next * smooth[:, None]
        amplitude = 0.5**octave
        total += amplitude * layer
        weight_sum += amplitude
    return total / weight_sum


def checker(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> Image:
    u, v = _uv(size)
    checks = int(rng.integers(4, 13))
    mask = ((np.floor(u * checks) + np.floor(v * checks)) % 2).astype(np.float64)
    return Image(_two_tone(mask, random_colour(rng, value=(0.05, 0.3)), random_colour(rng, value=(0.55, 0.85))))


def stripes(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> Image:
    u, v = _uv(size)
    count = int(rng.integers(3, 16))
    coordinate = u if rng.uniform() < 0.5 else v
    duty = rng.uniform(0.2, 0.6)
    mask = ((coordinate * count) % 1.0 < duty).astype(np.float64)
    return Image(_two_tone(mask, random_colour(rng), random_colour(rng)))


def noise(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> Image:
    mask = value_noise(rng, size)
    mask = np.clip((mask - mask.min()) / (np.ptp(mask) + 1e-9), 0.0, 1.0)
    return Image(_two_tone(mask, random_colour(rng, value=(0.1, 0.4)), random_colour(rng, value=(0.5, 0.85))))


def wood(rng: np.random.Generator, size: int = TEXTURE_SIZE) -> Image:
    """Growth rings: distance to a far-away trunk axis, perturbed by noise, folded into bands."""
    u, v = _uv(size)
    trunk = rng.uniform(-2.0, -1.0)
    distance = np.sqrt((u - trunk) ** 2 + 0.02 * (v - 0.5) ** 2)
    rings = (distance * rng.uniform(8.0, 20.0) + 0.8 * value_noise(rng, size, octaves=3, base=2)) % 1.0
    mask = np.clip(1.0 - np.abs(2.0 * rings - 1.0), 0.0, 1.0) ** 2
    dark = [rng.uniform(0.15, 0.3), rng.uniform(0.07, 0.14), rng.uniform(0.03, 0.06)]
    light = [rng.uniform(0.45, 0.65), rng.uniform(0.28, 0.4), rng.uniform(0.12, 0.22)]
    return Image(_two_tone(mask, dark, light))


PATTERNS = {"checker": checker, "stripes": stripes, "noise": noise, "wood": wood}
PATTERN_NAMES = tuple(sorted(PATTERNS))


def random_pattern(rng: np.random.Generator) -> Image:
    return PATTERNS[PATTERN_NAMES[int(rng.integers(len(PATTERN_NAMES)))]](rng)


def _lat_long_directions(size: tuple[int, int]) -> np.ndarray:
    """(H, W, 3) unit directions of a lat-long map's pixel centres, in Mitsuba's `envmap` layout."""
    height, width = size
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(width) + 0.5) / width * 2.0 * np.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], -1)


def sky(rng: np.random.Generator, size: tuple[int, int] = SKY_SIZE) -> Image:
    """A lat-long sky: zenith-to-horizon gradient, darker ground, and a soft sun disc.

    Rows follow Mitsuba's `envmap` (row 0 looks along +Y); the sun's brightness is bounded so
    scenes lit through a window stay within a sane exposure.
    """
    direction = _lat_long_directions(size)
    elevation = direction[..., 1]

    zenith = np.array([rng.uniform(0.15, 0.3), rng.uniform(0.3, 0.5), rng.uniform(0.7, 1.0)])
    horizon = np.array([rng.uniform(0.8, 1.0), rng.uniform(0.8, 1.0), rng.uniform(0.85, 1.0)])
    ground = np.array(random_colour(rng, saturation=(0.1, 0.4), value=(0.1, 0.3)))
    up = np.clip(elevation, 0.0, 1.0)[..., None] ** 0.5
    image = np.where(elevation[..., None] >= 0.0, (1.0 - up) * horizon + up * zenith, ground)

    sun_elevation, sun_azimuth = rng.uniform(0.15, 1.2), rng.uniform(0.0, 2.0 * np.pi)
    sun = np.array(
        [
            np.cos(sun_elevation) * np.sin(sun_azimuth),
            np.sin(sun_elevation),
            -np.cos(sun_elevation) * np.cos(sun_azimuth),
        ]
    )
    cosine = np.clip(direction @ sun, -1.0, 1.0)
    angular_radius = rng.uniform(0.05, 0.12)
    glow = np.exp(-((1.0 - cosine) / (1.0 - np.cos(angular_radius))))
    sun_colour = np.array([1.0, rng.uniform(0.85, 0.95), rng.uniform(0.7, 0.85)])
    image = image + rng.uniform(10.0, 30.0) * glow[..., None] * sun_colour
    return Image(image.astype(np.float32))


HDR_SKY_SIZE = (128, 256)


def hdr_sky(rng: np.random.Generator, size: tuple[int, int] = HDR_SKY_SIZE) -> Image:
    """A lat-long HDR map with sharp features: a hard-edged sun (0.5-2.5 degrees) that outshines the
    sky, a city skyline cutting the horizon, and hard-edged bright panels (softboxes, windows).

    The sun's radiance is set from its solid angle so its irradiance is 1-3x the sky's whatever its
    size: a small sun is a bright one, and its shadows are the sharper.
    """
    direction = _lat_long_directions(size)
    height, width = size
    elevation, azimuth = (
        np.arcsin(np.clip(direction[..., 1], -1.0, 1.0)),
        np.arctan2(direction[..., 0], -direction[..., 2]),
    )
    solid_angle = np.cos(elevation) * (np.pi / height) * (2.0 * np.pi / width)

    zenith = np.array(random_colour(rng, saturation=(0.3, 0.7), value=(0.3, 0.9)))
    horizon = np.array(random_colour(rng, saturation=(0.0, 0.3), value=(0.6, 1.0)))
    up = np.clip(direction[..., 1], 0.0, 1.0)[..., None] ** rng.uniform(0.3, 0.8)
    image = (1.0 - up) * horizon + up * zenith
    ground = np.array(random_colour(rng, saturation=(0.0, 0.4), value=(0.05, 0.3)))
    skyline = np.zeros(width)
    for _ in range(int(rng.integers(0, 12))):  # buildings: dark blocks rising from the horizon
        start, span = int(rng.integers(width)), int(rng.integers(2, width // 10))
        skyline[np.arange(start, start + span) % width] = np.maximum(
            skyline[np.arange(start, start + span) % width], rng.uniform(0.02, 0.25)
        )
    below = elevation < skyline[None, :]
    image = np.where(below[..., None], ground, image)

    for _ in range(int(rng.integers(0, 4))):  # bright hard-edged panels above the horizon
        centre_azimuth, centre_elevation = rng.uniform(-np.pi, np.pi), rng.uniform(0.1, 1.2)
        half_azimuth, half_elevation = rng.uniform(0.05, 0.3), rng.uniform(0.03, 0.2)
        offset = (azimuth - centre_azimuth + np.pi) % (2.0 * np.pi) - np.pi
        panel = (np.abs(offset) < half_azimuth) & (np.abs(elevation - centre_elevation) < half_elevation)
        image = np.where(
            panel[..., None], rng.uniform(2.0, 12.0) * np.array(random_colour(rng, (0.0, 0.2), (0.8, 1.0))), image
        )

    sun_elevation, sun_azimuth = rng.uniform(0.15, 1.2), rng.uniform(-np.pi, np.pi)
    sun = np.array(
        [
            np.cos(sun_elevation) * np.sin(sun_azimuth),
            np.sin(sun_elevation),
            -np.cos(sun_elevation) * np.cos(sun_azimuth),
        ]
    )
    cosine = direction @ sun
    disc = cosine > np.cos(np.deg2rad(rng.uniform(0.5, 2.5)))
    if not disc.any():  # smaller than a pixel: the pixel nearest the sun's direction
        disc = cosine == cosine.max()
    sky_irradiance = float(np.sum(image.mean(-1) * np.clip(direction[..., 1], 0.0, None) * solid_angle))
    sun_radiance = rng.uniform(1.0, 3.0) * sky_irradiance / float(np.sum(solid_angle[disc]))
    sun_colour = np.array([1.0, rng.uniform(0.85, 0.97), rng.uniform(0.7, 0.9)])
    image = np.where(disc[..., None], sun_radiance * sun_colour, image)
    return Image(image.astype(np.float32))
