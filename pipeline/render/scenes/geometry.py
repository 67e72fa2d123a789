"""4x4 transforms for Mitsuba's unit primitives, built in NumPy so descriptions stay variant-free.

Conventions follow Mitsuba: +Y is up; `rectangle` and `disk` lie in local XY facing +Z;
`cube` spans [-1, 1]^3; `look_at` puts the camera's viewing direction on local +Z.
"""

from __future__ import annotations

import numpy as np

from .plain import Matrix

UP = np.array([0.0, 1.0, 0.0])


def _unit(vector) -> np.ndarray:
    vector = np.asarray(vector, dtype=np.float64)
    return vector / np.sqrt(np.dot(vector, vector))


def _frame(x_axis, y_axis, z_axis, origin) -> Matrix:
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = x_axis, y_axis, z_axis, origin
    return Matrix(matrix)


def look_at(origin, target, up=UP) -> Matrix:
    """Camera-to-world matrix, identical to `mi.ScalarTransform4f().look_at`."""
    direction = _unit(np.subtract(target, origin))
    left = _unit(np.cross(up, direction))
    return _frame(left, np.cross(direction, left), direction, origin)


def planar(center, normal, v_direction, half_u: float, half_v: float) -> Matrix:
    """A rectangle/disk placement: facing `normal`, local Y along `v_direction` (made orthogonal).

    Local X is v x n, so (X, Y, n) is right-handed and the primitive's +Z normal lands on `normal`.
    """
    n = _unit(normal)
    v = np.asarray(v_direction, dtype=np.float64)
    if abs(np.dot(_unit(v), n)) > 0.99:  # nearly parallel: any other perpendicular will do
        v = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    v = _unit(v - np.dot(v, n) * n)
    u = np.cross(v, n)
    return _frame(u * half_u, v * half_v, n, center)


def box(center, half_extents, yaw_degrees: float = 0.0) -> Matrix:
    """A `cube` scaled to `half_extents` (x, y, z), turned about +Y, centred at `center`."""
    angle = np.deg2rad(yaw_degrees)
    cos, sin = np.cos(angle), np.sin(angle)
    rotation = np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]])
    half = np.asarray(half_extents, dtype=np.float64)
    return _frame(rotation[:, 0] * half[0], rotation[:, 1] * half[1], rotation[:, 2] * half[2], center)


def rotate_y_points(points: np.ndarray, yaw_degrees: float) -> np.ndarray:
    """Rotate (N, 3) points or normals about +Y (the same rotation as `box`)."""
    angle = np.deg2rad(yaw_degrees)
    cos, sin = np.cos(angle), np.sin(angle)
    rotation = np.array([[cos, 0.0, sin], [0.0, 1.0, 0.0], [-sin, 0.0, cos]])
    return points @ rotation.T
