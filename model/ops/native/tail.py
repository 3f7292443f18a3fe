"""The fused step's work after the network at 1x as one native pass (``tail.c``)."""

from __future__ import annotations

import torch

from model.ops import native

__all__ = ["fused_tail_x1"]


def fused_tail_x1(logits: torch.Tensor, candidates: list[torch.Tensor], trust: torch.Tensor | None,
                  valid: torch.Tensor, samples_count: torch.Tensor | None,
                  power: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """(the blend, the output in linear radiance, the sample mean's count kept) for one image, as ``Fused.step``
    computes them without an output kernel: the softmax of the 4 fusion ``logits``, the count times the history's
    share to ``power``, the weights moved by the stale-history ``trust`` (None: no test), and the blend of the 4
    ``candidates`` (OIDN's estimate, the history, the rectified history, the clipped mean)."""
    h, w = logits.shape[-2:]
    blended, output = logits.new_empty((1, 3, h, w)), logits.new_empty((1, 3, h, w))
    new_count = None if samples_count is None else logits.new_empty((1, 1, h, w))
    plain = [candidate.contiguous() for candidate in candidates]
    native.call("tail", "tail_x1", h, w, logits.contiguous(), *plain, None if trust is None else trust.contiguous(),
                valid.contiguous(), None if samples_count is None else samples_count.contiguous(), float(power),
                blended, output, new_count)
    return blended, output, new_count
