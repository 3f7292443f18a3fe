"""Conversions from a renderer's conventions to the frame bundle's (``model.io.frames``), one per buffer.

Pure NumPy; every function takes the renderer's array and the layout's convention and returns the frame bundle's.
"""

from __future__ import annotations

import math

import numpy as np

from model.io.frames import NORMAL_LENGTH_TOLERANCE, normal_lengths
from model.layouts.layout import DepthConvention, MotionConvention

# Lossy EXR compression (DWAA, B44) and half storage move unit normals off unit length by up to a few percent;
# within this much they are renormalised (and reported), beyond it they are refused as not normals at all.
NORMAL_REPAIR_TOLERANCE = 0.1


def motion_to_bundle(vectors: np.ndarray, convention: MotionConvention) -> np.ndarray:
    """(H, W, 2) vectors -> the frame bundle's motion: render pixels, y down, from this frame's sample to the
    previous frame's position."""
    height, width = vectors.shape[:2]
    motion = vectors.astype(np.float32, copy=True)
    if convention.units == "ndc":  # -1..1 spans the image: one unit is half the width (x) or height (y)
        motion[..., 0] *= width / 2
        motion[..., 1] *= height / 2
    if convention.y == "up":
        motion[..., 1] *= -1
    if convention.points_to == "current":
        motion *= -1
    return motion


def ray_length_factor(height: int, width: int, fov_y_degrees: float, jitter: tuple[float, float]) -> np.ndarray:
    """(H, W) ratio of the distance along each sample's ray to the distance along the view axis (>= 1), for a
    pinhole camera with square pixels and the given vertical field of view."""
    tan_y = math.tan(math.radians(fov_y_degrees) / 2)
    tan_x = tan_y * width / height
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    u = (xs + 0.5 + jitter[0] - width / 2) / (width / 2) * tan_x
    v = (ys + 0.5 + jitter[1] - height / 2) / (height / 2) * tan_y
    return np.sqrt(1.0 + u * u + v * v)


def depth_to_bundle(depth: np.ndarray, convention: DepthConvention, fov_y_degrees: float | None,
                    jitter: tuple[float, float]) -> np.ndarray:
    """(H, W) depth -> distance from the camera centre along the sample's ray, 0 where nothing is hit.

    ``fov_y_degrees`` is needed (not None) for planar depth; the caller finds it (option, layout or header).
    """
    depth = depth.astype(np.float32, copy=True)
    no_hit = np.zeros(depth.shape, bool)  # without a threshold, +Inf is a broken value (validator, sanitizer)
    if convention.no_hit_at_or_above is not None:
        no_hit = depth >= convention.no_hit_at_or_above
    if convention.kind == "planar":
        assert fov_y_degrees is not None, "planar depth needs the field of view"
        with np.errstate(invalid="ignore", over="ignore"):
            depth = (depth * ray_length_factor(*depth.shape, fov_y_degrees, jitter)).astype(np.float32)
    depth[no_hit] = 0.0
    return depth


def normals_to_world(normal: np.ndarray, world_to_camera: np.ndarray) -> np.ndarray:
    """View-space normals -> world space, given the header's 4x4 worldToCamera matrix.

    OpenEXR's matrices multiply row vectors (v_camera = v_world @ M), so v_world = v_camera @ inverse(M); only the
    3x3 rotation part matters for directions (the camera has no scale or shear).
    """
    rotation = np.asarray(world_to_camera, dtype=np.float64).reshape(4, 4)[:3, :3]
    return (normal.astype(np.float64) @ np.linalg.inv(rotation)).astype(np.float32)


def renormalise_normals(normal: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, int, float]:
    """Normals that the validator would refuse (off unit length by more than NORMAL_LENGTH_TOLERANCE) but within
    NORMAL_REPAIR_TOLERANCE of it (where depth > 0), scaled to unit length.

    Returns (normals, how many pixels were changed, the worst |n| among them). Pixels further off are left as they
    are, for the validator to refuse; so are non-finite ones (the sanitizer's business).
    """
    with np.errstate(invalid="ignore", over="ignore"):
        length = normal_lengths(normal)
        off = np.abs(length - 1.0)
        fixable = (depth > 0) & np.isfinite(length) & (off > NORMAL_LENGTH_TOLERANCE) & (off <= NORMAL_REPAIR_TOLERANCE)
    count = int(fixable.sum())
    if not count:
        return normal, 0, 1.0
    worst = float(length[fixable][np.argmax(off[fixable])])
    repaired = normal.copy()
    repaired[fixable] /= length[fixable][:, None]
    return repaired, count, worst
