"""WSKPN's weight-sharing kernels (Fan et al. 2021), evaluated without building k*k kernel maps.

WSKPN predicts ONE importance value per pixel q (per kernel size) and gives every pixel p whose k x k window
contains q the same weight w(q) for it (paper eq. 3-4, with w = exp(I)):

    out(p) = sum_{q in window(p)} w(q) c(q) / sum_{q in window(p)} w(q)  =  box_sum(w * c, k) / box_sum(w, k)

The weights do not depend on p, so this costs O(H W) per size (separable sums of shifted slices) instead of the
paper's unfold to an (N, k*k, H, W) kernel map. Pixels outside the image have weight 0: the window is clipped to
the image and renormalized (unfold with zero padding followed by softmax would darken borders). Kernel fusion
(paper eq. 5): several sizes k_i, each with its own importance map, are blended per pixel with softmax-normalized
weights alpha_i(p).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from model.ops.box_filter import box_sum

__all__ = ["box_sum", "weight_sharing_filter", "fuse_kernel_sizes", "weight_sharing_fused", "WSKPN_SIZES"]

WSKPN_SIZES = (3, 5, 7, 9, 11, 13)
"""The paper's kernel sizes for the BMFR setup: base 3, step 2, six sizes."""

# Logits more than this far below the sample's maximum are clamped, so exp() stays a normal float32
# (exp(-60) ~ 9e-27) and every window keeps a positive weight sum.
_LOGIT_RANGE = 60.0


def _importance_from_logits(logits: torch.Tensor) -> torch.Tensor:
    # Softmax is invariant to a constant shift; a per-sample max (not per window) keeps the weights shared.
    shift = logits.detach().amax(dim=(1, 2, 3), keepdim=True)
    return torch.exp((logits - shift).clamp_min(-_LOGIT_RANGE))


def weight_sharing_filter(
    image: torch.Tensor,
    importance: torch.Tensor,
    k: int,
    from_logits: bool = False,
) -> torch.Tensor:
    """Filter ``image`` (N, C, H, W) with a weight-sharing kernel of size k (odd, 1..): see the module docstring.

    importance: (N, 1, H, W) shared by all channels, or (N, C, H, W) per channel; positive weights w(q), or,
    with ``from_logits=True``, the network's raw I(q) with w = exp(I) computed stably (the paper's softmax).
    One call handles one kernel size; call once per size with that size's map (see :func:`weight_sharing_fused`).
    Windows whose total weight is 0 (only possible with non-positive importance) give 0, not NaN.
    Differentiable w.r.t. image and importance.
    """
    if k < 1 or k % 2 == 0:
        raise ValueError(f"k must be a positive odd integer, got {k}")
    if image.dim() != 4:
        raise ValueError(f"image must be (N, C, H, W), got {tuple(image.shape)}")
    n, c, h, w = image.shape
    if importance.dim() != 4 or importance.shape[0] != n or importance.shape[1] not in (1, c) or (
        importance.shape[-2:] != (h, w)
    ):
        raise ValueError(f"importance must be ({n}, 1 or {c}, {h}, {w}), got {tuple(importance.shape)}")
    importance = importance.to(image.dtype)
    weight = _importance_from_logits(importance) if from_logits else importance
    # One box pass over [w*c, w] stacked on channels (C+1 or 2C channels) instead of two calls.
    sums = box_sum(torch.cat([weight * image, weight], dim=1), k)
    num, den = sums[:, :c], sums[:, c:]
    return num / den.clamp_min(torch.finfo(den.dtype).tiny)


def fuse_kernel_sizes(outputs: Sequence[torch.Tensor], fusion_logits: torch.Tensor) -> torch.Tensor:
    """Per-pixel softmax blend of filtered images (paper eq. 5): sum_i softmax(fusion_logits)_i * outputs[i].

    outputs: M tensors (N, C, H, W); fusion_logits: (N, M, H, W).
    """
    if len(outputs) == 0:
        raise ValueError("need at least one output to fuse")
    n, _, h, w = outputs[0].shape
    if fusion_logits.shape != (n, len(outputs), h, w):
        raise ValueError(
            f"fusion_logits must have shape {(n, len(outputs), h, w)} for {len(outputs)} outputs, "
            f"got {tuple(fusion_logits.shape)}"
        )
    alpha = torch.softmax(fusion_logits.to(outputs[0].dtype), dim=1)
    fused = alpha[:, 0:1] * outputs[0]
    for i in range(1, len(outputs)):
        fused = fused + alpha[:, i : i + 1] * outputs[i]
    return fused


def weight_sharing_fused(
    image: torch.Tensor,
    importance_logits: torch.Tensor,
    fusion_logits: torch.Tensor,
    sizes: Sequence[int] = WSKPN_SIZES,
) -> torch.Tensor:
    """WSKPN's whole reconstruction: filter with each size's importance map, then fuse the results.

    image (N, C, H, W); importance_logits (N, M, H, W), channel i = I for ``sizes[i]``; fusion_logits (N, M, H, W).
    """
    m = len(sizes)
    if importance_logits.shape[1] != m:
        raise ValueError(f"importance_logits has {importance_logits.shape[1]} channels for {m} kernel sizes")
    outputs = [
        weight_sharing_filter(image, importance_logits[:, i : i + 1], k, from_logits=True)
        for i, k in enumerate(sizes)
    ]
    return fuse_kernel_sizes(outputs, fusion_logits)
