"""Valid frame bundles made up in memory, for drills and overhead benchmarks that exercise the service without a
dataset: their content means nothing to a denoiser (random normals, albedo and depth), only that every frame passes
validation, differs from the last and is reproducible from a seed.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from model.io.frames import FrameBundle

__all__ = ["moving_pattern_frames"]


def moving_pattern_frames(count: int, size: int | tuple[int, int], rng: np.random.Generator, *,
                          phases: Iterable[float] = (0, 2, 4), frequency: tuple[float, float] = (0.05, 0.03),
                          references: bool = False) -> list[FrameBundle]:
    """``count`` frames of ``size`` x ``size`` pixels (or ``size`` = (width, height)): a sine pattern that moves one pixel along x per frame, under
    exponential (1spp-like) noise, split into diffuse and specular; random unit normals, albedo and depth, a motion
    of -1 in x and y, a random jitter per frame.

    ``phases`` (one per color channel) and ``frequency`` (radians per pixel in x and y) shape the pattern: callers
    that stream several sequences at once draw other phases per sequence, so that a crossed history shows in the
    outputs. ``references`` adds the clean pattern as the scale-1 reference. All randomness comes from ``rng``.
    """
    phases = list(phases)
    width, height = (size, size) if isinstance(size, int) else size
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    fx, fy = frequency
    frames = []
    for index in range(count):
        clean = np.stack([0.5 + 0.4 * np.sin(fx * (xs + index) + fy * ys + p) for p in phases], 2).astype(np.float32)
        color = (clean * rng.exponential(1.0, size=clean.shape)).astype(np.float32)
        normal = rng.normal(size=(height, width, 3)).astype(np.float32)
        normal /= np.linalg.norm(normal, axis=2, keepdims=True)
        diffuse = (color * rng.uniform(0.2, 0.8, size=color.shape)).astype(np.float32)
        frames.append(FrameBundle(
            color=color, albedo=rng.uniform(0, 1, size=color.shape).astype(np.float32), normal=normal,
            depth=rng.uniform(1, 5, size=(height, width)).astype(np.float32),
            motion=np.full((height, width, 2), -1.0, np.float32),
            jitter=tuple(float(v) for v in rng.uniform(-0.5, 0.5, size=2)), frame_index=index,
            diffuse=diffuse, specular=color - diffuse, references={1: clean} if references else {}))
    return frames
