"""The fused step's reprojection at 1x as one native pass (``reproject.c``): the backward warps of
``model.ops.warp`` that share one motion, and the geometry test of ``model.ops.reproject``."""

from __future__ import annotations

import torch

from model.ops import native

__all__ = ["reproject_x1"]

# reproject.c reads up to this many images of each kind interleaved, one vector load a tap
CUBIC_STRIDE, LINEAR_STRIDE = 8, 16


def reproject_x1(motion: torch.Tensor, cubic: list[torch.Tensor], cubic_range: tuple[float, float],
                 linear: list[torch.Tensor], nearest: list[torch.Tensor], depth: torch.Tensor, normal: torch.Tensor,
                 prev_depth: torch.Tensor, prev_normal: torch.Tensor, jitter: torch.Tensor,
                 depth_rel_tol: float, normal_cos_tol: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor,
                                                                        torch.Tensor]:
    """For one image (N = 1): the ``cubic`` images read bicubic at ``centre + motion`` and clamped to
    ``cubic_range``, the ``linear`` ones bilinear, the ``nearest`` ones nearest (each concatenated along the
    channels, as one ``backward_warp`` each with border padding), and ``disocclusion_mask`` with ``jitter`` (1, 2)."""
    h, w = motion.shape[-2:]
    for images, most, kind in ((cubic, CUBIC_STRIDE, "bicubic"), (linear, LINEAR_STRIDE, "bilinear")):
        if sum(image.shape[1] for image in images) > most:
            raise ValueError(f"reproject_x1 reads at most {most} {kind} channels")
    outputs = []
    for images in (cubic, linear, nearest):
        channels = sum(image.shape[1] for image in images)
        outputs.append(motion.new_empty((1, channels, h, w)))
    valid = torch.empty((1, 1, h, w), dtype=torch.bool)
    jitter_x, jitter_y = (float(v) for v in jitter.reshape(2).tolist())
    native.call("reproject", "reproject_x1", h, w, motion.contiguous(),
                native.planes(*cubic), list(outputs[0][0]), outputs[0].shape[1], float(cubic_range[0]),
                float(cubic_range[1]),
                native.planes(*linear), list(outputs[1][0]), outputs[1].shape[1],
                native.planes(*nearest), list(outputs[2][0]), outputs[2].shape[1],
                depth.contiguous(), normal.contiguous(), prev_depth.contiguous(), prev_normal.contiguous(),
                jitter_x, jitter_y, float(depth_rel_tol), float(normal_cos_tol), valid,
                torch.empty(h * w * (CUBIC_STRIDE + LINEAR_STRIDE)))
    return outputs[0], outputs[1], outputs[2], valid
