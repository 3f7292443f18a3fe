"""Per-pixel kernel application (KPCN / AFN style): out(p) = sum_j w_j(p) * image(p + offset_j).

Kernel layout: ``kernels`` is (N, k*k, H, W); channel j = ky * k + kx holds the weight of the tap at offset
((kx - k//2) * dilation, (ky - k//2) * dilation) in (x, y), i.e. row-major over the window, top-left first. This
is the channel order of ``torch.nn.functional.unfold``, so kernels predicted for an unfold-based implementation
work unchanged. The same k*k weights apply to every image channel.

Borders: image values outside the image are 0 (zero padding). With ``normalize`` "softmax" or "sum" the
out-of-image taps are also left out of the normalization, so a normalized kernel is a partition of unity over
the taps that exist: a constant image stays constant up to the border instead of darkening there.

Implementation: a loop over the k*k offsets that accumulates ``w_j * shifted slice`` into one output, with a
hand-written backward doing the same loop in reverse. It is several times faster than ``F.unfold`` (which
materializes a C*k*k*H*W tensor) and than the same loop left to autograd (whose backward builds a padded zero
tensor per tap), forward and backward alike.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch.autograd.function import once_differentiable

__all__ = ["apply_pixel_kernels", "kernel_offsets"]

_NORMALIZE = ("none", "softmax", "sum")


def kernel_offsets(k: int, dilation: int = 1) -> list[tuple[int, int]]:
    """(dx, dy) of every kernel channel j, in channel order (row-major, top-left first)."""
    r = k // 2
    return [((j % k - r) * dilation, (j // k - r) * dilation) for j in range(k * k)]


def _slices(j: int, k: int, dilation: int, h: int, w: int) -> tuple[slice, slice]:
    # In the padded image, output pixel (y, x) tap j sits at (y + ky*d, x + kx*d).
    ky, kx = divmod(j, k)
    return slice(ky * dilation, ky * dilation + h), slice(kx * dilation, kx * dilation + w)


class _ApplyKernels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: torch.Tensor, kernels: torch.Tensor, k: int, dilation: int) -> torch.Tensor:
        h, w = image.shape[-2:]
        r = (k // 2) * dilation
        padded = F.pad(image, (r, r, r, r))
        out = None
        for j in range(k * k):
            sy, sx = _slices(j, k, dilation, h, w)
            tap = padded[..., sy, sx]
            wj = kernels[:, j : j + 1]
            if out is None:
                out = wj * tap
            else:
                out.addcmul_(wj, tap)
        ctx.save_for_backward(padded, kernels)
        ctx.k, ctx.dilation = k, dilation
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):
        padded, kernels = ctx.saved_tensors
        k, dilation = ctx.k, ctx.dilation
        h, w = grad.shape[-2:]
        r = (k // 2) * dilation
        grad = grad.contiguous()
        grad_image = grad_kernels = None
        if ctx.needs_input_grad[0]:
            # Adjoint of "gather from p + o_j": scatter grad * w_j back to p + o_j, then drop the padding.
            grad_padded = torch.zeros_like(padded)
            for j in range(k * k):
                sy, sx = _slices(j, k, dilation, h, w)
                grad_padded[..., sy, sx].addcmul_(grad, kernels[:, j : j + 1])
            grad_image = grad_padded[..., r : r + h, r : r + w]
        if ctx.needs_input_grad[1]:
            grad_kernels = torch.empty_like(kernels)
            for j in range(k * k):
                sy, sx = _slices(j, k, dilation, h, w)
                torch.sum(grad * padded[..., sy, sx], dim=1, out=grad_kernels[:, j])
        return grad_image, grad_kernels, None, None


def _apply(image: torch.Tensor, kernels: torch.Tensor, k: int, dilation: int) -> torch.Tensor:
    return _ApplyKernels.apply(image, kernels, k, dilation)


def apply_pixel_kernels(
    image: torch.Tensor,
    kernels: torch.Tensor,
    k: int,
    dilation: int = 1,
    normalize: str = "none",
    eps: float = 1e-8,
) -> torch.Tensor:
    """Filter ``image`` (N, C, H, W) with per-pixel k x k kernels ``kernels`` (N, k*k, H, W).

    normalize:
      - "none": use the weights as given (already normalized by the caller, or deliberately not).
      - "softmax": kernels are logits; weights = softmax over the taps that fall inside the image (WSKPN/KPCN).
      - "sum": weights divided by their sum over the in-image taps (clamped below at ``eps``; meant for
        non-negative weights, e.g. after a ReLU/softplus).
    Differentiable w.r.t. image and kernels (first order). See the module docstring for layout and borders.
    """
    if normalize not in _NORMALIZE:
        raise ValueError(f"normalize must be one of {_NORMALIZE}, got {normalize!r}")
    if k < 1 or k % 2 == 0:
        raise ValueError(f"k must be a positive odd integer, got {k}")
    if dilation < 1:
        raise ValueError(f"dilation must be >= 1, got {dilation}")
    if image.dim() != 4:
        raise ValueError(f"image must be (N, C, H, W), got {tuple(image.shape)}")
    n, _, h, w = image.shape
    if kernels.shape != (n, k * k, h, w):
        raise ValueError(f"kernels must have shape {(n, k * k, h, w)} for k={k}, got {tuple(kernels.shape)}")
    # Contiguous: a network in channels_last hands over a k*k-channel slice whose taps are strided by the channel
    # count, and every per-tap read below slows with it.
    kernels = kernels.to(image.dtype).contiguous()
    if normalize == "none":
        return _apply(image, kernels, k, dilation)

    # In-image indicator of every tap as an additive bias (0 inside, -inf outside), built separably from its row
    # and column parts: ~10x cheaper than unfolding an all-ones image and masking.
    bias = _outside_bias(k, dilation, h, w, image.dtype, image.device)
    if normalize == "softmax":
        # The max over in-image taps keeps exp() finite and makes the largest in-image weight exactly 1, so the
        # total below is >= 1 (a max taken over out-of-image taps too could underflow every real tap to 0).
        logits = kernels + bias
        logits = logits - logits.amax(dim=1, keepdim=True).detach()
        weights = logits.exp_()  # in place: saves a k*k-map allocation; exp's backward only needs its output
        total = weights.sum(dim=1, keepdim=True)
    else:
        weights = kernels * bias.exp()  # exp(-inf) = 0 drops out-of-image taps
        total = weights.sum(dim=1, keepdim=True).clamp_min(eps)
    return _apply(image, weights, k, dilation) / total


def _outside_bias(k: int, dilation: int, h: int, w: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(1, k*k, H, W): 0 where tap j of pixel (y, x) lies inside the image, -inf where it does not."""
    offsets = (torch.arange(k, device=device) - k // 2) * dilation

    def axis(size: int) -> torch.Tensor:  # (k, size): -inf where coordinate + offset leaves [0, size)
        pos = torch.arange(size, device=device).unsqueeze(0) + offsets.unsqueeze(1)
        out = torch.zeros((k, size), dtype=dtype, device=device)
        return out.masked_fill_((pos < 0) | (pos >= size), float("-inf"))

    return (axis(h).view(k, 1, h, 1) + axis(w).view(1, k, 1, w)).view(1, k * k, h, w)
