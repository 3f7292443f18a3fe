"""Resampling onto a grid ``scale`` times finer, shifted by a sub-pixel offset per item: ``F.grid_sample`` in two 1D
passes of shifted slices.

Output column X of the jitter resample at 2x reads source x = (X + 0.5) / scale - 0.5 + shift, the same for every row,
and output row Y reads one y: the read is separable. Better still, X = scale * k + p reads x = k + o_p with one
offset o_p per phase p, so each phase is a fixed filter over the source: a weighted sum of whole source images
shifted by whole pixels. With the shift bounded (the frame format's jitter lies in [-0.5, 0.5]) the set of those
shifts is known before the data: the slices are fixed, a tap out of a phase's reach gets the weight K(d) = 0, and
there is no branch on the data, so the read exports as it runs. The phases are then interleaved: much faster on the
CPU than index selections of the taps.

The arithmetic is the one ``grid_sample`` does with border padding and align_corners=False: cubic convolution with
A = -0.75, taps clamped to the image (here: the source padded by replicating its edges), x interpolated first, then
y. The bicubic weights come from the exact offsets o_p, so its outputs agree with grid_sample's to float rounding.
Nearest reads have one tap, so they stay index selections of whole columns and rows, at each position as grid_sample
computes it through its normalised grid: a position half-way between two pixels (Halton jitters land on quarters)
rounds half to even as grid_sample's does, also where that grid holds it inexactly, and the reads equal its own.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["cubic_kernel", "scaled_bicubic", "scaled_nearest"]

CUBIC_A = -0.75  # grid_sample's and OpenCV's cubic convolution constant
MAX_SHIFT = 0.5  # the largest |shift| the static tap sets cover; larger shifts are clamped to it


def cubic_kernel(d: torch.Tensor) -> torch.Tensor:
    """The cubic-convolution kernel K(d): the weight of a tap at distance ``d`` from the read position (0 past 2)."""
    a, d = CUBIC_A, d.abs()
    near = ((a + 2) * d - (a + 3)) * d * d + 1
    far = ((a * d - 5 * a) * d + 8 * a) * d - 4 * a
    return torch.where(d <= 1, near, torch.where(d < 2, far, torch.zeros_like(d)))


def _check(image: torch.Tensor, shift: torch.Tensor, scale: int) -> None:
    if image.dim() != 4:
        raise ValueError(f"image must be (N, C, H, W), got {tuple(image.shape)}")
    if shift.shape != (image.shape[0], 2):
        raise ValueError(f"shift must be (N, 2) with N = {image.shape[0]}, got {tuple(shift.shape)}")
    if isinstance(scale, bool) or not isinstance(scale, int) or scale < 1:
        raise ValueError(f"scale must be a whole number >= 1, got {scale!r}")


def _phase_offsets(shift: torch.Tensor, scale: int, dtype: torch.dtype) -> torch.Tensor:
    """o_p (N, scale): output k * scale + p reads source k + o_p along one axis, for that axis' shift (N,)."""
    phases = (torch.arange(scale, device=shift.device, dtype=dtype) + 0.5) / scale - 0.5
    return phases + shift.to(dtype).clamp(-MAX_SHIFT, MAX_SHIFT).unsqueeze(-1)


def _reach(scale: int, lowest: int, highest: int) -> list[range]:
    """Per phase, the whole-pixel shifts a read can use over every allowed shift, taps from floor(o) + ``lowest``
    to floor(o) + ``highest``."""
    reaches = []
    for p in range(scale):
        centre = (p + 0.5) / scale - 0.5
        reaches.append(range(math.floor(centre - MAX_SHIFT) + lowest, math.floor(centre + MAX_SHIFT) + highest + 1))
    return reaches


def _interleave(phases: list[torch.Tensor], dim: int) -> torch.Tensor:
    """The phases (each (N, C, H, W)) woven along ``dim``: output k * scale + p is phase p's k."""
    woven = torch.stack(phases, dim=dim + 1)
    shape = list(phases[0].shape)
    shape[dim] *= len(phases)
    return woven.reshape(shape)


def _padded(image: torch.Tensor, dim: int, pad: int) -> torch.Tensor:
    return F.pad(image, (pad, pad, 0, 0) if dim == 3 else (0, 0, pad, pad), mode="replicate")


def _bicubic_pass(image: torch.Tensor, offsets: torch.Tensor, dim: int) -> torch.Tensor:
    n, size = image.shape[0], image.shape[dim]
    reaches = _reach(offsets.shape[1], -1, 2)
    pad = max(max(-r.start, r.stop - 1) for r in reaches)
    padded = _padded(image, dim, pad)
    phases = []
    for p, reach in enumerate(reaches):
        shifts = torch.tensor(list(reach), device=image.device, dtype=offsets.dtype)
        weights = cubic_kernel(offsets[:, p:p + 1] - shifts).to(image.dtype)  # (N, taps); 0 for taps out of reach
        total = None
        for tap, whole in enumerate(reach):
            source, weight = padded.narrow(dim, pad + whole, size), weights[:, tap].view(n, 1, 1, 1)
            if total is None:
                total = source * weight
            else:
                total.addcmul_(source, weight)
        phases.append(total)
    return _interleave(phases, dim)


def _grid_sample_positions(shift: torch.Tensor, size: int, scale: int, dtype: torch.dtype) -> torch.Tensor:
    """(N, scale * size): the source position of every output pixel along one axis in grid_sample's own arithmetic
    (through its normalised grid), so that a position half-way between two pixels rounds as grid_sample's does."""
    centres = (torch.arange(size * scale, device=shift.device, dtype=dtype) + 0.5) / scale
    normalised = 2 * (centres + shift.to(dtype).clamp(-MAX_SHIFT, MAX_SHIFT).unsqueeze(-1)) / size - 1
    return (normalised + 1) * (size / 2) - 0.5


def _positions_dtype(image: torch.Tensor) -> torch.dtype:
    return torch.float64 if image.dtype == torch.float64 else torch.float32


def scaled_bicubic(image: torch.Tensor, shift: torch.Tensor, scale: int) -> torch.Tensor:
    """Bicubic read of ``image`` (N, C, H, W) onto the grid ``scale`` times finer whose pixel (X, Y) reads the source
    at ((X + 0.5) / scale - 0.5 + shift_x, (Y + 0.5) / scale - 0.5 + shift_y), in pixels (source pixel i's centre at
    i), border padding: what ``F.grid_sample(..., mode="bicubic", padding_mode="border", align_corners=False)`` reads
    there, (N, C, scale H, scale W). ``shift`` (N, 2) is clamped to [-0.5, 0.5]."""
    _check(image, shift, scale)
    dtype = _positions_dtype(image)
    columns = _bicubic_pass(image, _phase_offsets(shift[:, 0], scale, dtype), 3)
    return _bicubic_pass(columns, _phase_offsets(shift[:, 1], scale, dtype), 2)


def scaled_nearest(image: torch.Tensor, shift: torch.Tensor, scale: int) -> torch.Tensor:
    """Nearest read at the same positions as ``scaled_bicubic`` (grid_sample's mode="nearest", border padding: the
    position clamped to the image, then rounded half to even, as torch.round does)."""
    _check(image, shift, scale)
    dtype = _positions_dtype(image)
    h, w = image.shape[-2:]
    # Index selections of whole rows: a nearest read has one tap, so shifted slices gain nothing over them. The
    # columns are gathered with the index expanded over the channels and rows: index_select along the last dimension
    # is slow on this CPU, and so are the two transposed copies that would select them as rows.
    columns = torch.round(_grid_sample_positions(shift[:, 0], w, scale, dtype).clamp(0, w - 1)).long()
    rows = torch.round(_grid_sample_positions(shift[:, 1], h, scale, dtype).clamp(0, h - 1)).long()
    return torch.stack([torch.gather(item, 2, columns[i].expand(item.shape[0], h, -1)).index_select(1, rows[i])
                        for i, item in enumerate(image)])
