"""Box filters over each pixel's k x k window, from sums of shifted slices: the one place for them.

CPU torch does not optimise stride-1 average pooling, while adding whole frames is cheap. So every box filter here
is a separable sum of shifted slices, faster than pooling, without a summed-area table's float32 cancellation (a
running sum across a 1920-wide HDR row loses ~1e-7 of its total).

- ``box_sum``: the window's sum, zeros outside the image (WSKPN's weight-sharing filter; its backward is itself);
- ``box_mean``: the mean of the part of the window inside the image (avg_pool2d with count_include_pad=False; the
  stale-history tests);
- ``replicated_box_mean``: the mean with the image's edge pixels repeated past the border (the rectification's
  moments);
- ``replicated_box_extremes``: the window's max and min, edges repeated the same way (the rectification's clamp, the
  bounds of the fused 2x resample; faster than a stride-1 3x3 ``max_pool2d``).

Means over non-overlapping blocks are downsampling, not a window per pixel: ``model.ops.pyramid.block_mean``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

__all__ = ["box_mean", "box_sum", "replicated_box_extremes", "replicated_box_mean"]


def _window_sums(values: torch.Tensor, size: int, dim: int) -> torch.Tensor:
    """Sums of ``size`` consecutive entries along ``dim`` (length L - size + 1), by doubling: sums of 1, 2, 4, ...
    entries, then one of each binary digit of ``size``, so a 33-entry window takes 6 additions instead of 32 (a
    linear loop of them was a visible part of a fused step with the regional stale-history tests)."""
    if size == 1:
        return values.clone()  # a new tensor, as for every other size (never a view of the input)
    out_length = values.shape[dim] - size + 1
    total, offset, span, sums = None, 0, 1, values
    remaining = size
    while True:
        if remaining & 1:
            piece = sums.narrow(dim, offset, out_length)
            total = piece if total is None else total + piece
            offset += span
        remaining >>= 1
        if not remaining:
            return total
        length = sums.shape[dim] - span  # sums of 2 * span entries from those of span
        sums = sums.narrow(dim, 0, length) + sums.narrow(dim, span, length)
        span *= 2


def _box_sum_forward(x: torch.Tensor, k: int) -> torch.Tensor:
    r = k // 2
    padded = F.pad(x, (r, r, r, r))
    return _window_sums(_window_sums(padded, k, 3), k, 2)


class _BoxSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: torch.Tensor, k: int) -> torch.Tensor:
        ctx.k = k
        return _box_sum_forward(x, k)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        # A centred, zero-padded box sum is a symmetric linear map: it is its own adjoint.
        return _BoxSum.apply(grad.contiguous(), ctx.k), None


def _check(x: torch.Tensor, k: int) -> None:
    if k < 1 or k % 2 == 0:  # a window centred on its pixel
        raise ValueError(f"k must be a positive odd integer, got {k}")
    if x.dim() != 4:
        raise ValueError(f"expected (N, C, H, W), got {tuple(x.shape)}")


def box_sum(x: torch.Tensor, k: int) -> torch.Tensor:
    """Sum of each pixel's k x k window (k odd), zeros outside the image; (N, C, H, W) -> same shape."""
    _check(x, k)
    return _BoxSum.apply(x, k)


def _border_counts(length: int, size: int, like: torch.Tensor) -> torch.Tensor:
    """How many of each window's ``size`` positions lie inside a line of ``length`` pixels."""
    radius = size // 2
    index = torch.arange(length, device=like.device)
    return ((index + radius).clamp_max(length - 1) - (index - radius).clamp_min(0) + 1).to(like.dtype)


def box_mean(image: torch.Tensor, size: int) -> torch.Tensor:
    """Mean over each pixel's ``size`` x ``size`` window (odd) of the part inside the image, (N, C, H, W):
    ``avg_pool2d(image, size, stride=1, padding=size // 2, count_include_pad=False)``."""
    h, w = image.shape[-2:]
    sums = box_sum(image, size)
    return sums / (_border_counts(h, size, image).view(-1, 1) * _border_counts(w, size, image).view(1, -1))


def replicated_box_mean(image: torch.Tensor, size: int) -> torch.Tensor:
    """Mean over each pixel's ``size`` x ``size`` window with the image's edge pixels repeated past the border,
    (N, C, H, W): ``avg_pool2d(F.pad(image, (size // 2,) * 4, mode="replicate"), size, stride=1)``."""
    _check(image, size)
    r = size // 2
    padded = F.pad(image, (r, r, r, r), mode="replicate")  # the edge repeated: every window is whole
    return _window_sums(_window_sums(padded, size, 3), size, 2) / (size * size)


def replicated_box_extremes(image: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(max, min) over each pixel's ``size`` x ``size`` window with the edge pixels repeated past the border, each
    (N, C, H, W): the extremes of shifted views, along rows and then columns (exact, as any order of max is)."""
    _check(image, size)
    r = size // 2
    padded = F.pad(image, (r, r, r, r), mode="replicate")
    h, w = image.shape[-2:]
    extremes = []
    for pick in (torch.maximum, torch.minimum):
        rows = padded[..., 0:w]
        for i in range(1, size):
            rows = pick(rows, padded[..., i:i + w])
        out = rows[..., 0:h, :]
        for i in range(1, size):
            out = pick(out, rows[..., i:i + h, :])
        extremes.append(out)
    return extremes[0], extremes[1]
