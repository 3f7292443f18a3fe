"""The fused step's rectification at 1x as one native pass (``rectify.c``): the guide's 3x3 YCoCg moments, the box
``moment_bounds`` makes of them (gamma 1) and one or two images clipped to it (``clip_to_bounds``), for one image
(N = 1), without the moments or the box ever stored as frames."""

from __future__ import annotations

import torch

from model.ops import native

__all__ = ["clip_pair_x1"]


def clip_pair_x1(guide: torch.Tensor, first: torch.Tensor,
                 second: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``(clip_to_bounds(first, *box), clip_to_bounds(second, *box))`` with ``box = moment_bounds(
    *neighbourhood_moments(guide))``, each (1, 3, H, W); None for the second where ``second`` is None."""
    h, w = guide.shape[-2:]
    first_out = torch.empty_like(first, memory_format=torch.contiguous_format)
    second_out = None if second is None else torch.empty_like(second, memory_format=torch.contiguous_format)
    native.call("rectify", "clip_pair_x1", h, w, guide.contiguous(), first.contiguous(), first_out,
                None if second is None else second.contiguous(), second_out)
    return first_out, second_out
