"""Pinhole camera geometry: sub-pixel jitter, look-at frames and projection to image positions.

Pure NumPy so that motion vectors can be computed (and tested) without the renderer. The camera frame is
Mitsuba's `look_at` (columns: left, up, forward, origin), the field of view is horizontal, and image positions
follow `model.io.frames`: continuous pixels, origin at the top-left corner, x right, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def halton(index: int, base: int) -> float:
    """Radical inverse of `index` in `base` (index >= 1 gives values in (0, 1))."""
    result, fraction = 0.0, 1.0
    while index > 0:
        fraction /= base
        result += fraction * (index % base)
        index //= base
    return result


def frame_jitter(frame_index: int) -> tuple[float, float]:
    """TAA-style jitter in [-0.5, 0.5): Halton(2, 3) of frame_index + 1, minus 0.5."""
    return halton(frame_index + 1, 2) - 0.5, halton(frame_index + 1, 3) - 0.5


def look_at(origin, target, up) -> np.ndarray:
    """4x4 camera-to-world matrix, built exactly as Mitsuba's `Transform4f.look_at`."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    forward = target - origin
    forward /= np.linalg.norm(forward)
    left = np.cross(up, forward)
    norm = np.linalg.norm(left)
    if norm < 1e-9:
        raise ValueError(f"camera 'up' {up.tolist()} is parallel to the view direction")
    left /= norm
    new_up = np.cross(forward, left)
    matrix = np.eye(4)
    matrix[:3, 0], matrix[:3, 1], matrix[:3, 2], matrix[:3, 3] = left, new_up, forward, origin
    return matrix


@dataclass(frozen=True)
class Camera:
    """A pinhole camera; `fov` is the horizontal field of view in degrees."""

    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    fov: float = 45.0

    def to_world(self) -> np.ndarray:
        return look_at(self.origin, self.target, self.up)

    def project(self, points: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Image positions (N, 2) in pixels of world points (N, 3), and whether each lies in front of the camera.

        No jitter is applied: the projection itself does not move with the sample offset.
        """
        world_to_camera = np.linalg.inv(self.to_world())
        homogeneous = np.concatenate([points, np.ones((points.shape[0], 1))], axis=1)
        local = homogeneous @ world_to_camera.T
        z = local[:, 2]
        in_front = z > 1e-6
        safe_z = np.where(in_front, z, 1.0)
        half_width = np.tan(np.radians(self.fov) / 2.0)
        half_height = half_width * height / width
        # Camera-space x points left and y up, while image x runs right and y down: both flip.
        u = 0.5 - local[:, 0] / (2.0 * safe_z * half_width)
        v = 0.5 - local[:, 1] / (2.0 * safe_z * half_height)
        return np.stack([u * width, v * height], axis=1), in_front
