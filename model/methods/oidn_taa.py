"""OIDN + TAA: OIDN on every frame, then plain temporal anti-aliasing of the denoised frames. No learning.

What an experienced user builds first, and the bar every temporal method must clear. Per frame:
1. OIDN (the preset is OIDN's quality) denoises the 1 spp frame with its albedo and normal guides;
2. the previous output is reprojected by the motion vectors (bilinear) and dropped where the depth/normal test
   fails (`model.ops.reproject`) or after a camera cut;
3. both are tone-mapped with x / (1 + x), so a bright pixel cannot dominate the blend;
4. the history is clipped to the current frame's 3 x 3 neighbourhood mean +- 1 sigma in YCoCg
   (`model.ops.rectify.variance_clip`), which rejects most history that changing light made stale;
5. output = 0.2 * current + 0.8 * history, back to linear radiance.

At scale 2 the result is bicubic-upscaled (OIDN + TAA + bicubic). Its known failure: a light that moves fast
leaves history the neighbourhood box cannot reject (the box is wide where the light is).
"""

from __future__ import annotations

import torch

from model.methods.base import FrameBatch, State, drop_history
from model.methods.baselines import RenderResolutionFilter, reproject_state
from model.methods.oidn import QUALITIES, oidn_denoise
from model.methods.registry import MethodSpec, register
from model.ops.rectify import variance_clip

__all__ = ["OIDNTAA", "reinhard", "reinhard_inverse"]


def reinhard(x: torch.Tensor) -> torch.Tensor:
    """x / (1 + x): HDR radiance into [0, 1)."""
    return x / (1.0 + x)


def reinhard_inverse(y: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`reinhard` on [0, 1): y / (1 - y) (y is kept just below 1 so the result stays finite)."""
    y = y.clamp(0.0, 1.0 - 1e-6)
    return y / (1.0 - y)


class OIDNTAA(RenderResolutionFilter):
    """OIDN per frame, then TAA with variance clipping (the recipe in the module docstring)."""

    name = "oidn-taa"
    ALPHA = 0.2  # weight of the current frame
    GAMMA = 1.0  # clip box: neighbourhood mean +- GAMMA sigma
    WINDOW = 3

    def __init__(self, preset: str = "high", scale: int = 1, depth_rel_tol: float = 0.1,
                 normal_cos_tol: float = 0.9):
        super().__init__(preset, scale)
        if preset not in QUALITIES:
            raise KeyError(f"{self.name} has no preset {preset!r}; presets: {', '.join(QUALITIES)}")
        self.depth_rel_tol = depth_rel_tol
        self.normal_cos_tol = normal_cos_tol

    def filter_frame(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        current = reinhard(oidn_denoise(frame, self.preset))
        state = drop_history(state, frame)
        if state is None:
            blended = current
        else:
            warped, _, valid = reproject_state(frame, state, ("history",), self.depth_rel_tol, self.normal_cos_tol)
            history = variance_clip(warped["history"], current, self.WINDOW, self.GAMMA)
            blended = torch.where(valid, self.ALPHA * current + (1 - self.ALPHA) * history, current)
        new_state = {"history": blended, "count": torch.ones_like(frame.depth), "depth": frame.depth,
                     "normal": frame.normal, "jitter": frame.jitter}
        return reinhard_inverse(blended), new_state


register(MethodSpec(
    name=OIDNTAA.name,
    description="OIDN on each frame, then TAA (reprojection, depth test, YCoCg variance clip, alpha 0.2): "
                "the strongest non-learned peer",
    factory=lambda preset, scale: OIDNTAA(preset, scale),
    presets=QUALITIES,
    default_preset="high",
    scales=(1, 2),
    optional_buffers=("specular_albedo",),  # OIDN's albedo guide adds the specular albedo
))
