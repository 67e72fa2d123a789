"""Normals from a renderer's frame into admc's camera frame: x right, y up, z toward the viewer.

admc's networks read shading normals in that frame (an image flip is then a sign flip of a normal
component, which training's augmentation relies on). Renderers write normals in world space (Blender's
Normal pass, Mitsuba's `aov` integrator, pbrt-v4's gbuffer film with `"string coordinatesystem"
"world"`) or in their own camera frame (pbrt-v4's default and Cycles' Denoising Normal pass, both
z forward: measured on a Blender 5.0.1 render, the floor's normal (0, 0, 1) came out as (0, 0.95, -0.32)
for a camera pitched 72 degrees up).
A world-to-camera matrix names the camera; each renderer's camera frame differs from admc's by the
sign of some axes, which `CAMERA_FRAMES` records.
"""

from __future__ import annotations

import numpy as np

CAMERA_FRAMES = {
    "admc": (1.0, 1.0, 1.0),  # x right, y up, z toward the viewer (also Blender's camera object frame)
    "blender": (1.0, 1.0, 1.0),  # a Blender camera object looks down its local -z, y up
    "cycles": (1.0, 1.0, -1.0),  # Cycles' camera space (its Denoising Normal): x right, y up, z forward
    "pbrt": (1.0, 1.0, -1.0),  # pbrt-v4: x right, y up, z forward (left-handed)
    "mitsuba": (-1.0, 1.0, -1.0),  # Mitsuba's sensor frame: x left, y up, z forward
}
"""Per renderer camera frame, the signs that turn its axes into admc's."""


def to_admc_camera(normal: np.ndarray, frame: str) -> np.ndarray:
    """Normals given in a renderer's camera frame, in admc's."""
    return (np.asarray(normal, np.float32) * np.asarray(CAMERA_FRAMES[frame], np.float32)).astype(np.float32)


def world_to_admc_camera(normal: np.ndarray, world_to_camera: np.ndarray, frame: str) -> np.ndarray:
    """World-space normals (H, W, 3) into admc's camera frame, given the renderer's world-to-camera
    matrix (4x4 or 3x3, acting on column vectors) and the frame that matrix maps into.

    Normals transform by the inverse transpose of the matrix's linear part (a camera transform with
    a mirror or a scale, as in pbrt scenes that start with `Scale -1 1 1`, included) and keep their
    length: a pixel's mean normal is shorter than 1 where its samples saw different surfaces, as in
    admc's own renders; zero normals (pixels that hit nothing) stay zero.
    """
    linear = np.asarray(world_to_camera, np.float64).reshape(-1)
    linear = linear.reshape(4, 4)[:3, :3] if linear.size == 16 else linear.reshape(3, 3)
    normal_matrix = np.linalg.inv(linear).T
    normal = np.asarray(normal, np.float64)
    camera = normal @ normal_matrix.T
    length, before = np.linalg.norm(camera, axis=-1, keepdims=True), np.linalg.norm(normal, axis=-1, keepdims=True)
    camera = np.where(length > 0, camera * before / np.where(length > 0, length, 1.0), 0.0)
    return to_admc_camera(camera, frame)


def facing_share(normal: np.ndarray, tolerance: float = 0.2) -> tuple[float, int]:
    """Of the pixels with a normal in the image's central half (a quarter of its area), the share whose
    normal faces an admc camera (z > -tolerance), and how many pixels that is.

    A camera-space normal of a surface the camera sees faces the pixel's ray, which near the image's
    centre runs along -z; off-axis rays make a ceiling seen from a camera pitched down face away from the
    z axis although it faces its ray (measured on a Cycles interior: 10% of the whole image), hence the
    centre only. World-space normals face every way (a wall behind a floor, a ceiling)."""
    n = np.asarray(normal, np.float32)
    h, w = n.shape[:2]
    n = n[h // 4 : h - h // 4, w // 4 : w - w // 4].reshape(-1, 3)
    has = np.linalg.norm(n, axis=1) > 0.5
    count = int(has.sum())
    if count == 0:
        return 1.0, 0
    return float((n[has, 2] > -tolerance).mean()), count
