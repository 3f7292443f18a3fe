"""4x4 affine transforms in NumPy (column vectors: world = M @ local), for scene recipes and motion vectors."""

from __future__ import annotations

import numpy as np


def translate(x: float, y: float, z: float) -> np.ndarray:
    matrix = np.eye(4)
    matrix[:3, 3] = (x, y, z)
    return matrix


def scale(x: float, y: float | None = None, z: float | None = None) -> np.ndarray:
    return np.diag([x, x if y is None else y, x if z is None else z, 1.0])


def rotate(axis, degrees: float) -> np.ndarray:
    """Rotation about `axis` through the origin, right-handed (Rodrigues)."""
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    angle = np.radians(degrees)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    matrix = np.eye(4)
    matrix[:3, :3] = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * (cross @ cross)
    return matrix


def compose(*matrices: np.ndarray) -> np.ndarray:
    """compose(A, B, C) = A @ B @ C: C is applied first."""
    result = np.eye(4)
    for matrix in matrices:
        result = result @ matrix
    return result


def apply_to_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Transform (N, 3) points by a 4x4 affine matrix."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]
