"""Training losses over an unrolled sequence: SMAPE per frame plus an L1 loss on the frame-to-frame change.

Both terms are computed by default on log-tonemapped radiance, ``sign(x) log(1 + |x|)``: on linear HDR a few bright
pixels (lights, highlights, fireflies) would carry most of the temporal term, and the log map makes a flicker cost
by its relative size above 1 while staying nearly linear below 1, where the display-encoded metrics live; its
sign-preserving form keeps the loss finite for the negative outputs of early training. ``tonemap="mulaw"``
compresses harder (MUNet's curve), ``"linear"`` uses radiance as it is. An optional third term,
``display_weight * MSE`` on display-encoded images (the benchmark protocol's encoding), is the error PSNR measures:
SMAPE weighs a dark pixel's small error like a bright edge's large one, while the squared display error weighs
large visible errors (a ghost, a lagging highlight) most. Highlights above 1 are not compared by it (the display
clips them); the log terms still are.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from model.names import TONEMAPS
from model.ops.tonemap import display_encode, log_tonemap, mulaw

SMAPE_EPS = 0.01  # as in WSKPN and Vogels et al. 2018: bounds the loss of near-black pixels


def tonemap(x: torch.Tensor, kind: str) -> torch.Tensor:
    """Sign-preserving tone map ``sign(x) f(|x|)`` with f from ``model.ops.tonemap``; ``"linear"`` is the identity."""
    if kind == "linear":
        return x
    if kind == "log":
        return torch.sign(x) * log_tonemap(x.abs())
    if kind == "mulaw":
        return torch.sign(x) * mulaw(x.abs())
    raise ValueError(f"unknown tone map {kind!r}; choose from {', '.join(TONEMAPS)}")


def smape(output: torch.Tensor, target: torch.Tensor, eps: float = SMAPE_EPS) -> torch.Tensor:
    """Symmetric mean absolute percentage error, ``mean(|o - t| / (|o| + |t| + eps))`` over every element."""
    return ((output - target).abs() / (output.abs() + target.abs() + eps)).mean()


def temporal_gradient_l1(output: torch.Tensor, previous_output: torch.Tensor, target: torch.Tensor,
                         previous_target: torch.Tensor) -> torch.Tensor:
    """L1 between the frame-to-frame change of the output and of the target: flicker the target does not have."""
    return ((output - previous_output) - (target - previous_target)).abs().mean()


@dataclass
class LossTerms:
    total: torch.Tensor
    spatial: torch.Tensor
    temporal: torch.Tensor
    auxiliary: torch.Tensor | None = None  # the method's own extra term, already in total
    display: torch.Tensor | None = None  # display-encoded MSE (unweighted), when weighted in total

    def detached(self) -> dict[str, float]:
        values = {"loss": float(self.total.detach()), "spatial_loss": float(self.spatial.detach()),
                  "temporal_loss": float(self.temporal.detach())}
        if self.auxiliary is not None:
            values["auxiliary_loss"] = float(self.auxiliary.detach())
        if self.display is not None:
            values["display_loss"] = float(self.display.detach())
        return values


class SequenceLoss:
    """``spatial_weight * SMAPE + temporal_weight * temporal L1 (+ display_weight * display MSE)`` over T frames,
    each frame weighted.

    ``frame_weights`` (length T, default all 1) weight frame t's SMAPE and its temporal term (the change from
    t-1 to t; frame 0 has none); each term is a weighted mean over frames, so the weights' scale does not matter.
    """

    def __init__(self, spatial_weight: float = 1.0, temporal_weight: float = 0.25, tonemap: str = "log",
                 frame_weights: Sequence[float] | None = None, eps: float = SMAPE_EPS,
                 display_weight: float = 0.0) -> None:
        if tonemap not in TONEMAPS:
            raise ValueError(f"unknown tone map {tonemap!r}; choose from {', '.join(TONEMAPS)}")
        if spatial_weight < 0 or temporal_weight < 0 or display_weight < 0:
            raise ValueError(f"loss weights must be >= 0, got spatial {spatial_weight}, temporal {temporal_weight}, "
                             f"display {display_weight}")
        if frame_weights is not None and (min(frame_weights) < 0 or sum(frame_weights) <= 0):
            raise ValueError(f"frame weights must be >= 0 with a positive sum, got {list(frame_weights)}")
        self.spatial_weight = spatial_weight
        self.temporal_weight = temporal_weight
        self.display_weight = display_weight
        self.tonemap = tonemap
        self.frame_weights = None if frame_weights is None else [float(w) for w in frame_weights]
        self.eps = eps

    def __call__(self, outputs: Sequence[torch.Tensor], targets: Sequence[torch.Tensor],
                 auxiliary: torch.Tensor | None = None) -> LossTerms:
        """The weighted loss over T frames; a method's `auxiliary` term (see Method.auxiliary_loss) is added as is."""
        if len(outputs) != len(targets) or not outputs:
            raise ValueError(f"need as many outputs as targets (at least one), got {len(outputs)} and {len(targets)}")
        weights = self.frame_weights or [1.0] * len(outputs)
        if len(weights) != len(outputs):
            raise ValueError(f"{len(weights)} frame weights for a sequence of {len(outputs)} frames")
        mapped_outputs = [tonemap(o, self.tonemap) for o in outputs]
        mapped_targets = [tonemap(t, self.tonemap) for t in targets]

        frame_errors = [smape(o, t, self.eps) for o, t in zip(mapped_outputs, mapped_targets, strict=True)]
        spatial = _weighted_mean(frame_errors, weights)
        temporal_terms = [temporal_gradient_l1(mapped_outputs[t], mapped_outputs[t - 1],
                                               mapped_targets[t], mapped_targets[t - 1])
                          for t in range(1, len(outputs))]
        if temporal_terms and sum(weights[1:]) > 0:
            temporal = _weighted_mean(temporal_terms, weights[1:])
        else:  # one frame (or only frame 0 weighted): no change to compare
            temporal = spatial.new_zeros(())
        total = self.spatial_weight * spatial + self.temporal_weight * temporal
        display = None
        if self.display_weight > 0:
            display = _weighted_mean([(display_encode(o) - display_encode(t)).square().mean()
                                      for o, t in zip(outputs, targets, strict=True)], weights)
            total = total + self.display_weight * display
        if auxiliary is not None:
            total = total + auxiliary
        return LossTerms(total=total, spatial=spatial, temporal=temporal, auxiliary=auxiliary, display=display)


def _weighted_mean(terms: list[torch.Tensor], weights: Sequence[float]) -> torch.Tensor:
    return sum(w * term for w, term in zip(weights, terms, strict=True)) / sum(weights)
