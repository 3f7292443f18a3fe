"""History rectification: pull a reprojected history back into what the current frame says is plausible.

Reprojection cannot know that the lighting changed (a light moved, a highlight slid): motion vectors describe
geometry, so the warped history of such a pixel is wrong although the depth test passes. TAA's answer
(Salvi 2016, "An excursion in temporal supersampling") is to look at the current frame's neighbourhood: a
history colour far outside the colours around the pixel now is stale, so it is clipped to their range.

Both variants work per channel in YCoCg (luma and two chroma axes, decorrelated, so a box in that space fits
the neighbourhood's colours more tightly than one in RGB), over a k x k window, edges replicated:

- ``neighbourhood_clamp``: the box [min, max] of the window;
- ``variance_clip``: the box mean +- gamma * standard deviation of the window (gamma 1 is the classic recipe):
  tighter than min/max where the window holds an outlier, which noisy or spatially denoised input often does.

The guide should be low-noise (a spatially denoised frame, or the tone-mapped input of a converged method): on a
1 spp frame the window's spread is mostly noise and the box lets everything through.
"""

from __future__ import annotations

import torch

from model.ops.box_filter import replicated_box_extremes, replicated_box_mean

__all__ = ["rgb_to_ycocg", "ycocg_to_rgb", "neighbourhood_moments", "neighbourhood_clamp", "variance_clip",
           "clip_to_moments", "clip_to_bounds", "moment_bounds", "variance_clip_hdr", "rectify_accumulated",
           "ACCUMULATION_WINDOW", "ACCUMULATION_GAMMA"]

# The clip of an accumulated history against a 1 spp frame: a window wide enough that the noise does not make the
# box meaningless, and a box a little wider than TAA's (``accumulation:rectified``, ``svgf:rectified``, and the seed
# methods with ``rectify_history``).
ACCUMULATION_WINDOW, ACCUMULATION_GAMMA = 5, 1.5


def rgb_to_ycocg(rgb: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) RGB to YCoCg (Y = R/4 + G/2 + B/4, Co = R/2 - B/2, Cg = -R/4 + G/2 - B/4)."""
    r, g, b = rgb[:, 0:1], rgb[:, 1:2], rgb[:, 2:3]
    return torch.cat([0.25 * r + 0.5 * g + 0.25 * b, 0.5 * r - 0.5 * b, -0.25 * r + 0.5 * g - 0.25 * b], dim=1)


def ycocg_to_rgb(ycocg: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`rgb_to_ycocg` (exact: R = Y + Co - Cg, G = Y + Cg, B = Y - Co - Cg)."""
    y, co, cg = ycocg[:, 0:1], ycocg[:, 1:2], ycocg[:, 2:3]
    return torch.cat([y + co - cg, y + cg, y - co - cg], dim=1)


def _check(history: torch.Tensor, guide: torch.Tensor, size: int) -> None:
    if history.dim() != 4 or history.shape[1] != 3 or history.shape != guide.shape:
        raise ValueError(f"history and guide must both be (N, 3, H, W) of one shape, got {tuple(history.shape)} "
                         f"and {tuple(guide.shape)}")
    if size < 1 or size % 2 == 0:
        raise ValueError(f"window size must be odd and positive, got {size}")


def neighbourhood_moments(guide: torch.Tensor, size: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and standard deviation of the guide's YCoCg over each pixel's size x size window, (N, 3, H, W) each.

    Box means of the values and their squares (no k*k tensor, ``model.ops.box_filter``): this runs on every frame.
    """
    ycocg = rgb_to_ycocg(guide)
    moments = replicated_box_mean(torch.cat([ycocg, ycocg.square()], dim=1), size)
    mean, mean_sq = moments[:, :3], moments[:, 3:]
    return mean, (mean_sq - mean.square()).clamp_min(0.0).sqrt()


def neighbourhood_clamp(history: torch.Tensor, guide: torch.Tensor, size: int = 3) -> torch.Tensor:
    """Clamp the history, per YCoCg channel, to the min/max of the guide's size x size window; RGB out."""
    _check(history, guide, size)
    high, low = replicated_box_extremes(rgb_to_ycocg(guide), size)
    return ycocg_to_rgb(torch.maximum(torch.minimum(rgb_to_ycocg(history), high), low))


def variance_clip(history: torch.Tensor, guide: torch.Tensor, size: int = 3, gamma: float = 1.0) -> torch.Tensor:
    """Clamp the history, per YCoCg channel, to mean +- gamma * std of the guide's size x size window; RGB out."""
    _check(history, guide, size)
    if gamma < 0:
        raise ValueError(f"gamma must be >= 0, got {gamma}")
    return clip_to_moments(history, *neighbourhood_moments(guide, size), gamma)


def clip_to_moments(history: torch.Tensor, mean: torch.Tensor, std: torch.Tensor, gamma: float = 1.0) -> torch.Tensor:
    """``variance_clip`` against moments already taken (``neighbourhood_moments``): several histories clipped to one
    guide take its moments once."""
    return clip_to_bounds(history, *moment_bounds(mean, std, gamma))


def moment_bounds(mean: torch.Tensor, std: torch.Tensor, gamma: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The YCoCg box ``clip_to_moments`` clips to, (mean + gamma * std, mean - gamma * std): several histories
    clipped to one guide's box (``clip_to_bounds``) take it once."""
    spread = gamma * std
    return mean + spread, mean - spread


def clip_to_bounds(history: torch.Tensor, high: torch.Tensor, low: torch.Tensor) -> torch.Tensor:
    """Clamp the history, per YCoCg channel, to the box ``moment_bounds`` gives; RGB out."""
    return ycocg_to_rgb(torch.maximum(torch.minimum(rgb_to_ycocg(history), high), low))


def variance_clip_hdr(history: torch.Tensor, guide: torch.Tensor, size: int = 3, gamma: float = 1.0) -> torch.Tensor:
    """:func:`variance_clip` for linear HDR radiance: clipped in x / (1 + x) space, where one firefly or a bright
    light does not blow the window's sigma up to cover everything; linear radiance out."""
    tonemapped = variance_clip(history / (1.0 + history), guide / (1.0 + guide), size, gamma)
    tonemapped = tonemapped.clamp(0.0, 1.0 - 1e-6)
    return tonemapped / (1.0 - tonemapped)


def rectify_accumulated(history: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """An accumulated (linear HDR, demodulated) history clipped to the 1 spp ``current`` frame's neighbourhood:
    :func:`variance_clip_hdr` over ``ACCUMULATION_WINDOW`` pixels at ``ACCUMULATION_GAMMA`` sigma."""
    return variance_clip_hdr(history, current, ACCUMULATION_WINDOW, ACCUMULATION_GAMMA)
