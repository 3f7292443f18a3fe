"""The fused step's unjittered resample at 1x as one native pass (``resample.c``): ``sample_mean_resample`` and
``unjittered_resample`` of ``model.methods.fused`` for one image (N = 1), scale 1.

At 1x the read is a uniform sub-pixel shift of the whole image, so its cubic weights and its nearest indices are
one small table per axis. They are computed here by ``model.ops.separable_sample``'s own code, so the native reads
use the very weights and half-to-even roundings the torch path does."""

from __future__ import annotations

import functools

import torch

from model.ops import native
from model.ops.separable_sample import _grid_sample_positions, _phase_offsets, _reach, cubic_kernel

__all__ = ["sample_mean_resample_x1", "unjittered_resample_x1"]


@functools.lru_cache(maxsize=256)  # the jitter sequence repeats: its tables are a quarter of a call's time otherwise
def _axis_tables(shift: float, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Along one axis at 1x, for a shift: the cubic weights of the whole-pixel taps -2..2 (5,) and the index each
    output pixel reads nearest (size,) int32, as ``scaled_bicubic`` and ``scaled_nearest`` take them."""
    shift = torch.tensor([shift], dtype=torch.float32)
    (reach,) = _reach(1, -1, 2)
    taps = torch.tensor(list(reach), dtype=torch.float32)
    weights = cubic_kernel(_phase_offsets(shift, 1, torch.float32)[:, 0:1] - taps).to(torch.float32)[0]
    positions = _grid_sample_positions(shift, size, 1, torch.float32).clamp(0, size - 1)
    return weights.contiguous(), torch.round(positions)[0].to(torch.int32).contiguous()


def _resample(image: torch.Tensor, jitter: torch.Tensor, count: torch.Tensor | None) -> torch.Tensor:
    h, w = image.shape[-2:]
    shift_x, shift_y = (-jitter.to(torch.float32)).reshape(2).tolist()  # float32 values, exact as Python floats
    wx, columns = _axis_tables(shift_x, w)
    wy, rows = _axis_tables(shift_y, h)
    out = torch.empty_like(image, memory_format=torch.contiguous_format)
    native.call("resample", "resample_x1", h, w, image.contiguous(),
                None if count is None else count.contiguous(), wx, wy, columns, rows, out)
    return out


def sample_mean_resample_x1(image: torch.Tensor, jitter: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """``sample_mean_resample(image, jitter, count, 1)`` for ``image`` (1, 3, H, W), ``jitter`` (1, 2) and
    ``count`` (1, 1, H, W)."""
    return _resample(image, jitter, count)


def unjittered_resample_x1(image: torch.Tensor, jitter: torch.Tensor) -> torch.Tensor:
    """``unjittered_resample(image, jitter, 1)`` for ``image`` (1, 3, H, W) and ``jitter`` (1, 2)."""
    return _resample(image, jitter, None)
