"""The albedo on the target grid, gathered from jittered frames, and the texture detail it holds past the render
resolution.

At scale s, a frame's sample of render pixel x lies at x + 0.5 + j render pixels (j: the frame's jitter), which is
target pixel s x + floor(s (0.5 + j)): the jitter is one per frame, so every sample of a frame lands on the same
sub-pixel phase. The guides are noise-free, so one sample is the albedo at that point, and over frames with
different jitters every target pixel gathers samples of its own. Their running mean estimates the albedo's mean
over the target pixel, which is what the reference's box-filtered albedo at the target resolution holds.

Radiance is albedo times shading, and where albedo carries texture (a brick wall's mortar, a checker floor) the
shading is smooth at that scale. A denoised estimate made at the render resolution and resampled to the target
holds the albedo's render-pixel average; multiplied by the ratio of the gathered albedo to its own render-pixel
average, resampled the same way (``texture_detail``), it gets the texture back.

A sample on a sub-pixel boundary says nothing about which side holds what, and is not gathered. A renderer without
jitter writes every sample at the pixel centre, which at 2x is the corner of four target pixels: its frames gather
nothing and leave the detail at 1.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from model.ops.pyramid import block_mean
from model.ops.separable_sample import scaled_bicubic

__all__ = ["BOUNDARY", "DETAIL_BOUNDS", "DETAIL_OFFSET", "DETAIL_SAMPLES", "gather_samples", "sample_weights",
           "splat_at_jitter", "texture_detail"]

BOUNDARY = 0.05  # samples nearer than this to a sub-pixel edge (in target pixels) are not gathered
DETAIL_OFFSET = 0.02  # added to both albedos of the ratio: where albedo is near black, a small difference stays small
DETAIL_SAMPLES = 2.0  # a target pixel's detail is trusted as n / (n + this) of its n gathered samples
DETAIL_BOUNDS = (0.5, 2.0)  # the ratio's clamp: a few samples across an albedo edge never scale the output further


def _check_scale(scale: int) -> None:
    if isinstance(scale, bool) or not isinstance(scale, int) or scale < 2:
        raise ValueError(f"scale must be a whole number >= 2 (a target grid finer than the render), got {scale!r}")


def sample_weights(jitter: torch.Tensor, scale: int, height: int, width: int,
                   boundary: float = BOUNDARY) -> torch.Tensor:
    """(N, 1, scale height, scale width): 1 in the target pixel each render pixel's sample lies in at the frame's
    ``jitter`` (N, 2) in [-0.5, 0.5], 0 in the other sub-pixels, and 0 everywhere for a frame whose sample lies
    within ``boundary`` of a sub-pixel edge."""
    _check_scale(scale)
    if jitter.dim() != 2 or jitter.shape[1] != 2:
        raise ValueError(f"jitter must be (N, 2), got {tuple(jitter.shape)}")
    n = jitter.shape[0]
    dtype = jitter.dtype if jitter.is_floating_point() else torch.float32
    position = scale * (0.5 + jitter.to(dtype).clamp(-0.5, 0.5))  # (N, 2) in [0, s]: where in the pixel
    fraction = position - torch.floor(position)
    clear = (torch.minimum(fraction, 1 - fraction) >= boundary).all(dim=1).to(dtype)  # (N,)
    phase = torch.floor(position).clamp(0, scale - 1)
    sub = torch.arange(scale, device=jitter.device, dtype=dtype)
    columns, rows = (sub == phase[:, :1]).to(dtype), (sub == phase[:, 1:]).to(dtype)  # (N, s) one-hot
    # The weights are the one sub-pixel of every s x s block: that block's pattern tiled over the image.
    pattern = rows[:, :, None] * columns[:, None, :] * clear.view(n, 1, 1)
    return pattern.unsqueeze(1).repeat(1, 1, height, width)


def splat_at_jitter(image: torch.Tensor, jitter: torch.Tensor, scale: int,
                    boundary: float = BOUNDARY) -> tuple[torch.Tensor, torch.Tensor]:
    """(sum (N, C, sH, sW), weight (N, 1, sH, sW)): each render pixel's value of ``image`` (N, C, H, W) put in the
    target pixel its sample lies in (``sample_weights``), 0 elsewhere."""
    _check_scale(scale)
    if image.dim() != 4 or jitter.shape != (image.shape[0], 2):
        raise ValueError(f"image must be (N, C, H, W) and jitter (N, 2), got {tuple(image.shape)} and "
                         f"{tuple(jitter.shape)}")
    weight = sample_weights(jitter.to(image.dtype), scale, image.shape[2], image.shape[3], boundary)
    return F.interpolate(image, scale_factor=scale, mode="nearest") * weight, weight


def gather_samples(total: torch.Tensor, weight: torch.Tensor, new_total: torch.Tensor, new_weight: torch.Tensor,
                   window: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The sums of a running mean over up to ``window`` frames' samples, this frame's added: the previous weight is
    capped at window - 1 (its sum scaled with it) first, so the mean is exact over the first frames and then an
    exponential average, which forgets a texture that changed (an object moved onto it)."""
    if isinstance(window, bool) or not isinstance(window, int) or window < 1:
        raise ValueError(f"window must be a whole number of frames >= 1, got {window!r}")
    cap = float(window - 1)
    kept = torch.where(weight > cap, cap / weight.clamp_min(1e-12), torch.ones_like(weight))
    return total * kept + new_total, weight * kept + new_weight


def texture_detail(total: torch.Tensor, weight: torch.Tensor, fallback: torch.Tensor, scale: int,
                   offset: float = DETAIL_OFFSET, samples: float = DETAIL_SAMPLES,
                   bounds: tuple[float, float] = DETAIL_BOUNDS) -> torch.Tensor:
    """The factor (N, C, sH, sW) that puts the gathered albedo's detail into an estimate resampled from the render
    resolution: the gathered mean (``total / weight``; ``fallback`` where nothing was gathered) over its own
    render-pixel means read back bicubically (as a 2x resample reads), each plus ``offset``, clamped to ``bounds``,
    and trusted n / (n + ``samples``) of the way from 1 by a pixel's n gathered samples."""
    _check_scale(scale)
    gathered = torch.where(weight > 0, total / weight.clamp_min(1e-12), fallback)
    means = block_mean(gathered, scale)
    smooth = scaled_bicubic(means, means.new_zeros(means.shape[0], 2), scale)  # F.interpolate's bicubic, in phases
    ratio = ((gathered + offset) / (smooth.clamp_min(0) + offset)).clamp(*bounds)
    trust = weight / (weight + samples)
    return 1 + trust * (ratio - 1)
