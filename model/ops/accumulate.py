"""Exponential temporal accumulation with a per-pixel sample count (SVGF-style).

Every input here is already in the current frame's pixel grid: ``history`` is the previous accumulated result
backward-warped with ``warp.backward_warp`` and ``valid`` comes from ``reproject.disocclusion_mask``. Keeping the
warp out of this module lets each method choose its own filter for the history (bilinear, bicubic).

Per pixel, with n the new sample count:

    n     = min(history_count + 1, max_count)  where valid, else 1   (a failed pixel restarts from its 1 sample)
    alpha = max(1 / n, alpha_min)
    out   = alpha * current + (1 - alpha) * history

While n < 1 / alpha_min this is the exact running mean of the n samples; afterwards it becomes an exponential
moving average, so old (possibly stale: moving light, shading change) history fades at a bounded rate.
The count itself is a useful network input (MUNet encodes it), hence it keeps growing past 1 / alpha_min unless
``max_count`` caps it.
"""

from __future__ import annotations

import torch

from model.ops.tonemap import luminance

__all__ = ["update_count", "accumulate", "accumulate_moments"]


def _as_bool(valid: torch.Tensor) -> torch.Tensor:
    return valid if valid.dtype == torch.bool else valid > 0.5


def update_count(
    history_count: torch.Tensor | None,
    valid: torch.Tensor | None,
    max_count: float | None = None,
    like: torch.Tensor | None = None,
) -> torch.Tensor:
    """New per-pixel sample count (N, 1, H, W): ``where(valid, min(history_count + 1, max_count), 1)``.

    ``history_count=None`` (first frame, or a cut) gives all ones shaped/typed like ``like`` (N, C, H, W).
    ``valid`` may be bool or float (> 0.5 means valid).
    """
    if history_count is None:
        if like is None:
            raise ValueError("update_count needs `like` when history_count is None")
        n, _, h, w = like.shape
        return torch.ones((n, 1, h, w), dtype=like.dtype, device=like.device)
    if valid is None:
        raise ValueError("valid is required when history is given")
    count = history_count + 1
    if max_count is not None:
        count = count.clamp_max(max_count)
    return torch.where(_as_bool(valid), count, torch.ones_like(count))


def _blend_weight(count: torch.Tensor, alpha_min: float) -> torch.Tensor:
    return torch.maximum(1.0 / count, torch.full_like(count, alpha_min))


def _blend(current: torch.Tensor, history: torch.Tensor, alpha: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    blended = alpha * current + (1.0 - alpha) * history
    # where(), not just alpha = 1: invalid history may hold NaN/garbage (off-image reads) and 0 * NaN = NaN.
    return torch.where(_as_bool(valid), blended, current)


def accumulate(
    current: torch.Tensor,
    history: torch.Tensor | None,
    history_count: torch.Tensor | None,
    valid: torch.Tensor | None,
    alpha_min: float = 0.1,
    max_count: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend the current frame (N, C, H, W) into the reprojected history; returns ``(accumulated, count)``.

    history (N, C, H, W) and history_count (N, 1, H, W) are the previous frame's outputs warped to this frame;
    ``history=None`` starts fresh (output = current, count = 1). Differentiable in ``current`` and ``history``.
    """
    if not 0.0 < alpha_min <= 1.0:
        raise ValueError(f"alpha_min must be in (0, 1], got {alpha_min}")
    if history is None:
        return current, update_count(None, None, like=current)
    if history.shape != current.shape:
        raise ValueError(f"history shape {tuple(history.shape)} != current shape {tuple(current.shape)}")
    if history_count is None:
        raise ValueError("history_count is required when history is given")
    count = update_count(history_count, valid, max_count)
    alpha = _blend_weight(count, alpha_min)
    return _blend(current, history, alpha, valid), count


def accumulate_moments(
    current: torch.Tensor,
    history_mean: torch.Tensor | None,
    history_mean_sq: torch.Tensor | None,
    history_count: torch.Tensor | None,
    valid: torch.Tensor | None,
    alpha_min: float = 0.2,
    max_count: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Accumulate the first two moments of luminance (SVGF's temporal variance estimate).

    current: linear RGB (N, 3, H, W), reduced with Rec. 709 weights, or an already single-channel (N, 1, H, W)
    signal. The moments use the same count rule as :func:`accumulate` (pass the same history_count / valid so
    both stay in step) with their own ``alpha_min`` (SVGF uses 0.2 for moments vs 0.1 for color: variance
    needs to react faster).

    Returns ``(mean, mean_sq, variance)``, each (N, 1, H, W), variance = max(mean_sq - mean^2, 0). With few
    samples (count < ~4) this estimate is unreliable; SVGF then estimates variance spatially instead.
    """
    if not 0.0 < alpha_min <= 1.0:
        raise ValueError(f"alpha_min must be in (0, 1], got {alpha_min}")
    lum = current if current.shape[1] == 1 else luminance(current)
    lum_sq = lum * lum
    if history_mean is None or history_mean_sq is None:
        mean, mean_sq = lum, lum_sq
    else:
        if history_count is None:
            raise ValueError("history_count is required when history moments are given")
        count = update_count(history_count, valid, max_count)
        alpha = _blend_weight(count, alpha_min)
        mean = _blend(lum, history_mean, alpha, valid)
        mean_sq = _blend(lum_sq, history_mean_sq, alpha, valid)
    variance = (mean_sq - mean * mean).clamp_min(0.0)
    return mean, mean_sq, variance
