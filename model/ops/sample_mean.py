"""A running mean of the 1 spp frames themselves, for a spatial denoiser to read instead of the single frame.

OIDN on one sample per pixel loses texture it cannot tell from noise; on the mean of a few frames' samples (where
the scene holds still) it keeps more of it. Unlike a mean of the denoiser's outputs, whose blur does not average out,
this one averages the unbiased samples. Per pixel, with ``count`` the frames the reprojected mean already holds:

    trust = history_trust(stale_history_z(noisy, mean), sigmas)      (1 where sigmas is 0: no test)
    n     = min(count * trust + 1, max_frames)   where the history is valid, else 1
    mean  = noisy / n + (1 - 1 / n) * mean

so a mean that the new samples contradict (a moving light) restarts, as does one the geometry test rejects.

The frame may carry more channels after its three colour ones: the guides of the same samples (albedo, normals).
They are averaged with the same weights, since OIDN asks for guides that cover the same samples as the colour;
the test reads the colour alone.
"""

from __future__ import annotations

import torch

from model.ops.stale_history import history_trust, stale_history_z

__all__ = ["update_sample_mean"]


def update_sample_mean(noisy: torch.Tensor, mean: torch.Tensor, count: torch.Tensor, valid: torch.Tensor,
                       max_frames: int, stale_sigmas: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """(new mean, frames it holds) from this frame's samples ``noisy`` (N, C, H, W), C >= 3 with the colour first,
    and the previous mean and count warped into this frame (``mean`` (N, C, H, W), ``count`` (N, 1, H, W));
    ``valid`` (N, 1, H, W) bool marks where that history may be used."""
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    if noisy.dim() != 4 or noisy.shape[1] < 3 or noisy.shape != mean.shape:
        raise ValueError(f"noisy and mean must both be (N, C >= 3, H, W) of one shape, got {tuple(noisy.shape)} and "
                         f"{tuple(mean.shape)}")
    if stale_sigmas > 0:
        count = count * history_trust(stale_history_z(noisy[:, :3], mean[:, :3]), stale_sigmas)
    count = torch.where(valid, count, torch.zeros_like(count))
    count = (count + 1).clamp_max(float(max_frames))
    return noisy / count + (1 - 1 / count) * mean, count
