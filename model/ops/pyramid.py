"""2x resampling and image pyramids (multi-scale kernel filtering, AFN/MR-KP scale compositing, U-Nets).

Geometry follows the pixel-footprint convention: coarse pixel (i, j) covers fine pixels (2i..2i+1, 2j..2j+1),
so coarse continuous coordinate u maps to fine coordinate 2u (align_corners=False everywhere).

Odd sizes: ``downsample2x`` replicates the last row/column before averaging (the last coarse pixel is then the
mean of the one fine row/column it covers), giving ceil(H/2) x ceil(W/2); ``upsample2x(..., size=(H, W))`` crops
the 2x result back to the fine size, so a 720p frame can go through any number of levels and come back.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["block_mean", "downsample2x", "upsample2x", "build_pyramid"]


def block_mean(x: torch.Tensor, factor: int) -> torch.Tensor:
    """The mean of each ``factor`` x ``factor`` block, (N, C, H, W) -> (N, C, H / factor, W / factor): what
    ``F.avg_pool2d(x, factor)`` computes, to the bit in float32 and float64 (the same sum in the same order, then
    the same division). CPU torch does not vectorise that pooling, and the sum of the strided views is much
    faster. Other dtypes keep the pooling, which accumulates them in float."""
    if x.dim() != 4:
        raise ValueError(f"expected (N, C, H, W), got {tuple(x.shape)}")
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise ValueError(f"factor must be a whole number >= 1, got {factor!r}")
    h, w = x.shape[-2:]
    if h % factor or w % factor:
        raise ValueError(f"a {h}x{w} image is not made of whole {factor}x{factor} blocks")
    if factor == 1:
        return x
    if x.dtype not in (torch.float32, torch.float64):
        return F.avg_pool2d(x, factor)
    total = None
    for dy in range(factor):  # row-major over the block, as the pooling sums it
        for dx in range(factor):
            view = x[..., dy::factor, dx::factor]
            total = view if total is None else total + view
    return total / (factor * factor)


def downsample2x(x: torch.Tensor) -> torch.Tensor:
    """2x2 box mean, (N, C, H, W) -> (N, C, ceil(H/2), ceil(W/2)); odd sizes replicate the last row/column."""
    if x.dim() != 4:
        raise ValueError(f"expected (N, C, H, W), got {tuple(x.shape)}")
    h, w = x.shape[-2:]
    if h % 2 or w % 2:
        x = F.pad(x, (0, w % 2, 0, h % 2), mode="replicate")
    return block_mean(x, 2)


def upsample2x(x: torch.Tensor, mode: str = "bilinear", size: tuple[int, int] | None = None) -> torch.Tensor:
    """2x upsampling with align_corners=False semantics; optional crop to ``size`` (H, W) <= 2x the input.

    "nearest" copies each pixel into its 2x2 block (the WSKPN/AFN U operator); "bilinear" interpolates between
    pixel centres and clamps at the border (torch's align_corners=False behaviour).
    """
    if x.dim() != 4:
        raise ValueError(f"expected (N, C, H, W), got {tuple(x.shape)}")
    if mode == "nearest":
        up = F.interpolate(x, scale_factor=2, mode="nearest-exact")
    elif mode == "bilinear":
        up = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
    else:
        raise ValueError(f"mode must be 'bilinear' or 'nearest', got {mode!r}")
    if size is not None:
        h, w = size
        if h > up.shape[-2] or w > up.shape[-1] or h < up.shape[-2] - 1 or w < up.shape[-1] - 1:
            raise ValueError(f"size {size} is not the fine size of a {tuple(x.shape[-2:])} coarse image")
        up = up[..., :h, :w]
    return up


def build_pyramid(x: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """[x, downsample2x(x), downsample2x^2(x), ...]: ``levels`` images, finest first (levels >= 1)."""
    if levels < 1:
        raise ValueError(f"levels must be >= 1, got {levels}")
    out = [x]
    for _ in range(levels - 1):
        out.append(downsample2x(out[-1]))
    return out
