"""A running mean of the 1 spp frames themselves, for a spatial denoiser to read instead of the single frame.

OIDN on one sample per pixel loses texture it cannot tell from noise; on the mean of a few frames' samples (where
the scene holds still) it keeps more of it. Unlike a mean of the denoiser's outputs, whose blur does not average out,
this one averages the unbiased samples. Per pixel, with ``count`` the frames the reprojected mean already holds:

    trust = stale_history_trust(noisy, mean, sigmas, region)         (1 where sigmas is 0: no test)
    n     = min(count * trust * (1 - spread) + 1, max_frames)   where the history is valid, else 1
    mean  = noisy / n + (1 - 1 / n) * mean

so a mean that the new samples contradict (a moving light) restarts, as does one the geometry test rejects.
``spread`` is how much reading the mean into this frame blurred it (``model.ops.warp.bilinear_spread``, 0 where
nothing moved): a mean resampled at half a pixel every frame piles up that blur, which OIDN cannot undo, so there it
keeps only as many frames as the blur is worth.

The frame may carry more channels after its three colour ones: the guides of the same samples (albedo, normals).
They are averaged with the same weights, since OIDN asks for guides that cover the same samples as the colour;
the test reads the colour alone.
"""

from __future__ import annotations

import torch

from model.ops import native
from model.ops.native.stale import sample_mean_update
from model.ops.stale_history import stale_history_trust
from model.ops.warp import bilinear_spread

__all__ = ["JITTERED_SPREAD_SHARE", "sample_mean_spread", "update_sample_mean"]

# Chosen on the validation recipes (jittered) and Blender Cycles' frames (no jitter).
JITTERED_SPREAD_SHARE = 0.5


def sample_mean_spread(motion: torch.Tensor, jitter: torch.Tensor, previous_jitter: torch.Tensor) -> torch.Tensor:
    """The ``spread`` of ``update_sample_mean`` for a mean warped bilinearly by ``motion`` (N, 2, H, W): the warp's
    blur (``bilinear_spread``), counted in full for frames without jitter (this frame and the one before both
    sampled at the pixel centre, ``jitter`` and ``previous_jitter`` (N, 2) zero) and at ``JITTERED_SPREAD_SHARE``
    otherwise: a jittered frame pays for part of the blur with samples at new sub-pixel positions."""
    jittered = (jitter != 0).any(dim=1) | (previous_jitter != 0).any(dim=1)
    share = torch.where(jittered, JITTERED_SPREAD_SHARE, 1.0).to(motion.dtype).view(-1, 1, 1, 1)
    return bilinear_spread(motion) * share


def update_sample_mean(noisy: torch.Tensor, mean: torch.Tensor, count: torch.Tensor, valid: torch.Tensor,
                       max_frames: int, stale_sigmas: float = 0.0,
                       spread: torch.Tensor | None = None, stale_region: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(new mean, frames it holds) from this frame's samples ``noisy`` (N, C, H, W), C >= 3 with the colour first,
    and the previous mean and count warped into this frame (``mean`` (N, C, H, W), ``count`` (N, 1, H, W));
    ``valid`` (N, 1, H, W) bool marks where that history may be used; ``spread`` (N, 1, H, W) in [0, 1], the blur
    of that warp (None: none); ``stale_region``: the regional test's window (``stale_history_trust``; 0: none)."""
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    if noisy.dim() != 4 or noisy.shape[1] < 3 or noisy.shape != mean.shape:
        raise ValueError(f"noisy and mean must both be (N, C >= 3, H, W) of one shape, got {tuple(noisy.shape)} and "
                         f"{tuple(mean.shape)}")
    one = (1, 1) + tuple(noisy.shape[-2:])  # one image: the count arithmetic and the update in one native pass
    if (noisy.shape[0] == 1 and count.shape == one and valid.shape == one and valid.dtype == torch.bool
            and (spread is None or spread.shape == one) and native.usable("stale", noisy, mean, count)
            and (spread is None or native.usable("stale", spread))):
        trust = None
        if stale_sigmas > 0:
            trust = stale_history_trust(noisy[:, :3], mean[:, :3], stale_sigmas, stale_region)
        return sample_mean_update(noisy, mean, count, valid, max_frames, trust, spread)
    if stale_sigmas > 0:
        count = count * stale_history_trust(noisy[:, :3], mean[:, :3], stale_sigmas, stale_region)
    if spread is not None:
        if spread.shape != count.shape:
            raise ValueError(f"spread must have the count's shape {tuple(count.shape)}, got {tuple(spread.shape)}")
        count = count * (1 - spread.clamp(0, 1))
    count = torch.where(valid, count, torch.zeros_like(count))
    count = (count + 1).clamp_max(float(max_frames))
    return noisy / count + (1 - 1 / count) * mean, count
