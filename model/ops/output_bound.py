"""The output bound every method's step ends with: no output brighter than its frame's input allows, none non-finite.

A method's output at a pixel is an estimate of the mean radiance there, and no pixel of the converged image is
brighter than the brightest radiance the frame's own samples see, so a step's output is clamped per sample to
``[0, OUTPUT_BOUND_FACTOR * peak]``, ``peak`` the largest finite value of the frame's noisy input color (never below
``OUTPUT_BOUND_FLOOR``, so a black or nearly black frame keeps headroom). NaN becomes 0. The clamp is a no-op for
any output within the bound, so it changes nothing but the blow-ups it exists for: inverse tone maps such as
``y / (1 - y)`` amplify a network output near 1 into radiance far above anything the scene holds.

``Method`` applies it after every subclass's ``step`` (model/methods/base.py), so training, evaluation, sessions and
exported steps all run it. docs/methods.md ("Output bound") gives the reasoning and the factor's choice.
"""

from __future__ import annotations

import torch

__all__ = ["OUTPUT_BOUND_FACTOR", "OUTPUT_BOUND_FLOOR", "input_peak", "output_bound", "bound_output", "output_ratio"]

OUTPUT_BOUND_FACTOR = 1.0
"""Outputs never exceed this times the frame's brightest finite input value."""

OUTPUT_BOUND_FLOOR = 1.0
"""The peak used for a frame whose brightest input is below this (linear radiance)."""


def input_peak(color: torch.Tensor) -> torch.Tensor:
    """The largest finite value of each sample's (N, C, H, W) input, (N, 1, 1, 1); 0 for an all non-finite one."""
    finite = torch.nan_to_num(color, nan=0.0, posinf=0.0, neginf=0.0)
    return finite.flatten(1).amax(dim=1).view(-1, 1, 1, 1)


def output_bound(color: torch.Tensor, factor: float = OUTPUT_BOUND_FACTOR,
                 floor: float = OUTPUT_BOUND_FLOOR) -> torch.Tensor:
    """The largest output radiance allowed per sample for input ``color``: (N, 1, 1, 1)."""
    return factor * input_peak(color).clamp_min(floor)


def bound_output(output: torch.Tensor, color: torch.Tensor, factor: float = OUTPUT_BOUND_FACTOR,
                 floor: float = OUTPUT_BOUND_FLOOR) -> torch.Tensor:
    """``output`` with NaN set to 0 and clamped to ``[0, output_bound(color)]`` per sample (any resolution)."""
    # Elementwise passes only (no torch.where over the image): the bound runs on every frame of every session.
    bound = output_bound(color, factor, floor).to(output.dtype)
    return torch.minimum(torch.nan_to_num(output, nan=0.0).clamp_min(0.0), bound)


def output_ratio(output: torch.Tensor, color: torch.Tensor) -> float:
    """Brightest output over brightest finite input (at least ``OUTPUT_BOUND_FLOOR``), the worst over the batch:
    what the bound keeps at or below ``OUTPUT_BOUND_FACTOR``. Infinite for a non-finite output."""
    if not bool(torch.isfinite(output).all()):
        return float("inf")
    peaks = output.flatten(1).amax(dim=1) / input_peak(color).flatten().clamp_min(OUTPUT_BOUND_FLOOR)
    return float(peaks.max())
