"""Small rendered sequences shared by the data tests (rendered once per session: rendering is the slow part)."""

from __future__ import annotations

import numpy as np
import pytest

from model.data.mitsuba_backend import find_llvm

requires_llvm = pytest.mark.skipif(find_llvm() is None, reason="Mitsuba's llvm_ad_rgb needs libLLVM-19")


def render_frames(scene: str, frames: int, size: tuple[int, int], ref_spp: int, seed: int = 0,
                  ref_scales=(1, 2), render_seed: int | None = None, only: list[int] | None = None,
                  jitter: bool = True):
    """Render `frames` frames of recipe `scene` (or just the frame indices in `only`)."""
    from model.data.render import RenderSettings, SceneRenderer
    from model.data.scenes import build_scene

    settings = RenderSettings(width=size[0], height=size[1], ref_spp=ref_spp, ref_scales=tuple(ref_scales),
                              jitter=jitter)
    renderer = SceneRenderer(build_scene(scene, seed, frames), settings,
                             seed if render_seed is None else render_seed)
    return [renderer.render_frame(i) for i in (range(frames) if only is None else only)]


@pytest.fixture(scope="session")
def fast_camera_frames():
    return render_frames("fast_camera", 3, (48, 40), ref_spp=256, seed=3)


@pytest.fixture(scope="session")
def moving_object_frames():
    # Ten frames keep the per-frame motion moderate; two adjacent ones are enough.
    return render_frames("moving_object", 10, (48, 40), ref_spp=256, seed=5, only=[4, 5])


def display(image: np.ndarray) -> np.ndarray:
    return np.clip(image, 0.0, 1.0) ** (1.0 / 2.2)


def psnr(image: np.ndarray, reference: np.ndarray) -> float:
    """PSNR on display-encoded images, as the benchmark protocol computes it."""
    return float(10.0 * np.log10(1.0 / np.mean((display(image) - display(reference)) ** 2)))
