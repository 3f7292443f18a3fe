"""Widening a trained fused network without changing what it computes, so a fine-tune starts from its function.

Every convolution of ``FusionNet`` gets ``width - old`` more output channels (twice that at the bottom level),
with fresh random weights; every old channel reads the new ones with weight zero, and so does the head. The new
channels therefore change nothing until training moves those zeros (their gradients are not zero: the new
channels' activations are not), and the widened model's first validation equals its source's.
"""

from __future__ import annotations

import torch

from model.methods.fused import CANDIDATES, HIDDEN, LEGACY_CANDIDATES, FusionNet, head_candidates

__all__ = ["widened_state_dict"]

# (layer, input layout) per convolution: how the old input channels sit among the new ones.
_LAYERS = (("net.encoder.0.0", "inputs"), ("net.encoder.1.0", "top"), ("net.bottom.0.0", "top"),
           ("net.bottom.1.0", "bottom"), ("net.decoder.0", "skip"), ("net.head", "top"))


def widened_state_dict(state_dict: dict[str, torch.Tensor], width: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A fused model's state dict with its network widened to ``width`` channels at the top level (``2 * width``
    at the bottom), computing the same function; ValueError unless ``width`` is wider than the model's."""
    old = state_dict["net.head.weight"].shape[1]
    if isinstance(width, bool) or not isinstance(width, int) or width <= old:
        raise ValueError(f"a widened network needs more than the model's {old} channels, got {width!r}")
    inputs = state_dict["net.encoder.0.0.weight"].shape[1]
    scale, candidates = _scale_and_candidates(state_dict["net.head.weight"].shape[0])
    with torch.random.fork_rng(devices=[]):  # the caller's random state stays as it was
        torch.manual_seed(seed)
        fresh = FusionNet(inputs, scale, width=width, candidates=candidates).state_dict()
    grown = dict(state_dict)
    for layer, layout in _LAYERS:
        weight, bias = state_dict[f"{layer}.weight"], state_dict[f"{layer}.bias"]
        new_weight = fresh[layer.removeprefix("net.") + ".weight"].clone()
        new_bias = torch.zeros_like(fresh[layer.removeprefix("net.") + ".bias"])
        rows = weight.shape[0]
        columns = _old_columns(layout, old, width, inputs)
        new_weight[:rows] = 0.0  # old outputs read nothing from the new channels
        new_weight[:rows, columns] = weight
        new_bias[:rows] = bias
        grown[f"{layer}.weight"], grown[f"{layer}.bias"] = new_weight, new_bias
    return grown


def _old_columns(layout: str, old: int, width: int, inputs: int) -> torch.Tensor:
    """Where the old network's input channels of a layer sit among the widened layer's."""
    if layout == "inputs":
        return torch.arange(inputs)
    if layout == "top":
        return torch.arange(old)
    if layout == "bottom":
        return torch.arange(2 * old)
    # The decoder reads [top (width), upsampled bottom (2 * width)].
    return torch.cat([torch.arange(old), width + torch.arange(2 * old)])


def _scale_and_candidates(head_rows: int) -> tuple[int, int]:
    """(scale, candidates) of a fused network's head: 16 or 17 outputs at 1x, 52 or 56 at 2x."""
    for scale in (1, 2):
        candidates = head_candidates(head_rows, scale)
        if (head_rows - HIDDEN) % scale ** 2 == 0 and candidates in (LEGACY_CANDIDATES, CANDIDATES):
            return scale, candidates
    raise ValueError(f"not a fused network's state dict (its head has {head_rows} outputs)")
