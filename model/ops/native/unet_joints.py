"""The fused network's pooling and its upsampling with the concatenation, in bfloat16 channels_last, as native
passes (``unet_joints.c``): torch's kernels for these in bfloat16 are slow on the CPU."""

from __future__ import annotations

import torch

from model.ops import native

__all__ = ["joints_usable", "mean_pool2", "upsample_cat"]


def joints_usable(image: torch.Tensor) -> bool:
    """Whether ``image`` (a network activation) is one bfloat16 channels_last image the native joints take."""
    return image.shape[0] == 1 and image.is_contiguous(memory_format=torch.channels_last) \
        and native.usable("unet_joints", image, dtype=torch.bfloat16)


def mean_pool2(image: torch.Tensor) -> torch.Tensor:
    """``F.avg_pool2d(image, 2, ceil_mode=True)`` for ``joints_usable`` images."""
    _, c, h, w = image.shape
    out = torch.empty((1, c, (h + 1) // 2, (w + 1) // 2), dtype=torch.bfloat16, memory_format=torch.channels_last)
    native.call("unet_joints", "mean_pool2_bf16", h, w, c, image, out)
    return out


def upsample_cat(fine: torch.Tensor, coarse: torch.Tensor) -> torch.Tensor:
    """``torch.cat([fine, F.interpolate(coarse, size=fine's, mode="bilinear", align_corners=False)], dim=1)`` for
    ``joints_usable`` images, channels_last."""
    _, c_fine, h, w = fine.shape
    _, c_coarse, hc, wc = coarse.shape
    out = torch.empty((1, c_fine + c_coarse, h, w), dtype=torch.bfloat16, memory_format=torch.channels_last)
    native.call("unet_joints", "upsample_cat_bf16", h, w, c_fine, fine, hc, wc, c_coarse, coarse, out)
    return out
