"""The fused step's work between OIDN and the network at 1x as one native pass (``features.c``)."""

from __future__ import annotations

import torch

from model.ops import native

__all__ = ["FEATURES", "fused_features_x1"]

FEATURES = 35  # the fused network's inputs at 1x with a running mean (model.methods.fused)


def _plain(image: torch.Tensor | None) -> torch.Tensor | None:
    return None if image is None else image.contiguous()


def fused_features_x1(s: torch.Tensor, s_out: torch.Tensor, color: torch.Tensor, albedo: torch.Tensor,
                      normal: torch.Tensor, history: torch.Tensor | None, valid: torch.Tensor | None,
                      length: torch.Tensor | None, hidden: torch.Tensor | None, mean: torch.Tensor | None,
                      count: torch.Tensor | None, depth: torch.Tensor, depth_max: torch.Tensor, max_history: float,
                      count_norm: torch.Tensor, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, ...]:
    """(history, rectified history, running mean, clipped mean, history length, network input in channels_last,
    float32 or bfloat16 as ``dtype`` says) for one image, as ``Fused._network_inputs`` computes them; ``history``
    None: no state (the first frame), ``mean`` None: no running mean in the state. The reprojected buffers come from
    ``Fused._reproject``."""
    if dtype not in (torch.float32, torch.bfloat16):
        raise ValueError(f"the network input is float32 or bfloat16, not {dtype}")
    h, w = s.shape[-2:]
    outputs = [s.new_empty((1, c, h, w)) for c in (3, 3, 3, 3, 1)]
    features = torch.empty((1, FEATURES, h, w), dtype=dtype, memory_format=torch.channels_last)
    native.call("features", "features_x1", h, w, s.contiguous(), s_out.contiguous(), color.contiguous(),
                albedo.contiguous(), normal.contiguous(), _plain(history), _plain(valid), _plain(length),
                _plain(hidden), _plain(mean), _plain(count), depth.contiguous(), float(depth_max.item()),
                float(max_history), float(count_norm.item()), *outputs, features, dtype == torch.bfloat16)
    return (*outputs, features)
