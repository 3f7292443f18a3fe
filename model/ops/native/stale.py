"""The stale-history test (``model.ops.stale_history``) and the sample-mean update (``model.ops.sample_mean``) as
native passes for one image (``stale.c``)."""

from __future__ import annotations

import torch

from model.ops import native

__all__ = ["sample_mean_update", "stale_trust"]


def stale_trust(noisy: torch.Tensor, history: torch.Tensor, sigmas: float, region: int, block: int,
                relative_floor: float, region_cap: float, region_sigmas: float) -> torch.Tensor:
    """``stale_history_trust`` of ``noisy`` and ``history`` (1, 3, H, W), with that module's constants passed in;
    (1, 1, H, W)."""
    h, w = noisy.shape[-2:]
    trust = noisy.new_empty((1, 1, h, w))
    native.call("stale", "stale_trust", h, w, native.planes(noisy), native.planes(history),
                float(sigmas), int(block), int(region), float(relative_floor), float(region_cap),
                float(region_sigmas), trust)
    return trust


def sample_mean_update(noisy: torch.Tensor, mean: torch.Tensor, count: torch.Tensor, valid: torch.Tensor,
                       max_frames: int, trust: torch.Tensor | None,
                       spread: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """``update_sample_mean``'s count arithmetic and mean update for one image: ``noisy`` and ``mean`` (1, C, H, W),
    ``count``, ``valid`` (bool), ``trust`` and ``spread`` (1, 1, H, W; None: not applied); (new mean, count)."""
    h, w = noisy.shape[-2:]
    out_mean, out_count = torch.empty_like(noisy, memory_format=torch.contiguous_format), count.new_empty((1, 1, h, w))
    native.call("stale", "sample_mean_update", h, w, noisy.shape[1], native.planes(noisy), native.planes(mean),
                count.contiguous(), None if trust is None else trust.contiguous(),
                None if spread is None else spread.contiguous(), valid.contiguous(), float(max_frames),
                list(out_mean[0]), out_count)
    return out_mean, out_count
