"""Measure a fused model's output with its low band taken from OIDN's estimate of the frame itself, against the model
as it is (findings: docs/results/findings.md).

    .venv/bin/python experiments/try_lowband_correction.py --data data/reuse --split test --model fused-balanced-x1 \
        --vdp

Where a light moves, the fused models' history lags behind the shading over whole regions, and FovVideoVDP finds that
coherent lag more visible than OIDN's error, which changes every frame. OIDN's estimate of this frame does not lag.
Each variant keeps the model's output F above a Gaussian blur of ``sigma`` pixels and takes the estimate O (OIDN at
the model's quality, read at the pixel centres) below it, as a ratio in x / (1 + x):
``F * (1 + g * ((G*O + c) / (G*F + c) - 1))``, with ``g`` the gate:
- ``none``: 1 everywhere;
- ``difference``: 1 - exp(-(d / threshold)^2), d the luminance difference of the two low bands;
- ``stale``: 1 minus the stale-history test's trust of the output against the 1 spp frame
  (``model.ops.stale_history``: 9 x 9 windows, a 33-pixel region) at ``threshold`` standard errors.

The history is the model's own, untouched: the correction is on the output only. Evaluates in one run, on the same
frames (``model.evaluation.evaluate``, fp32 eager): the model, each variant (``--variant GATE:SIGMA:THRESHOLD``, repeatable),
OIDN + TAA at the model's OIDN quality and OIDN-high.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.evaluation.evaluate import evaluate, format_table, resolve_method  # noqa: E402
from model.methods.base import FrameBatch, Method, State  # noqa: E402
from model.methods.fused import unjittered_resample  # noqa: E402
from model.methods.oidn import oidn_denoise  # noqa: E402
from model.methods.oidn_taa import reinhard, reinhard_inverse  # noqa: E402
from model.ops.rectify import rgb_to_ycocg  # noqa: E402
from model.ops.stale_history import stale_history_trust  # noqa: E402

GATES = ("none", "difference", "stale")
RATIO_OFFSET = 0.01  # keeps the ratio of two dark low bands near 1 (values are x / (1 + x), in [0, 1))
STALE_REGION = 33  # the shipped models' regional test window


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian of standard deviation ``sigma`` pixels (3 sigma each side), edges repeated."""
    radius = max(1, math.ceil(3 * sigma))
    taps = torch.exp(-torch.arange(-radius, radius + 1, dtype=image.dtype) ** 2 / (2 * sigma ** 2))
    taps = (taps / taps.sum()).to(image.device)
    channels = image.shape[1]
    rows = F.conv2d(F.pad(image, (radius, radius, 0, 0), mode="replicate"),
                    taps.view(1, 1, 1, -1).repeat(channels, 1, 1, 1), groups=channels)
    return F.conv2d(F.pad(rows, (0, 0, radius, radius), mode="replicate"),
                    taps.view(1, 1, -1, 1).repeat(channels, 1, 1, 1), groups=channels)


def low_band_corrected(output: torch.Tensor, estimate: torch.Tensor, gate: torch.Tensor | float,
                       sigma: float) -> torch.Tensor:
    """``output``'s detail over ``estimate``'s low band, weighted by ``gate`` (linear radiance in and out)."""
    mapped = reinhard(output)
    low_output, low_estimate = gaussian_blur(mapped, sigma), gaussian_blur(reinhard(estimate), sigma)
    ratio = (low_estimate + RATIO_OFFSET) / (low_output + RATIO_OFFSET)
    return reinhard_inverse((mapped * (1 + gate * (ratio - 1))).clamp(0.0, 1.0 - 1e-4))


def gate_of(kind: str, threshold: float, sigma: float, frame: FrameBatch, output: torch.Tensor,
            estimate: torch.Tensor) -> torch.Tensor | float:
    if kind == "none":
        return 1.0
    if kind == "difference":
        # the luma of YCoCg, the space the project's clips work in
        low = gaussian_blur(reinhard(estimate), sigma) - gaussian_blur(reinhard(output), sigma)
        difference = rgb_to_ycocg(low)[:, :1]
        return 1 - torch.exp(-(difference / threshold) ** 2)
    return 1 - stale_history_trust(frame.color, output, threshold, STALE_REGION)


class LowBandCorrected(Method):
    """A 1x model whose output takes its low band from OIDN's estimate of the frame (see the module docstring)."""

    name = "lowband"

    def __init__(self, model: Method, gate: str, sigma: float, threshold: float):
        if model.name != "fused" or model.scale != 1:
            raise ValueError(f"{model.label}: needs a 1x fused model (a shipped fused-*-x1 or its checkpoint)")
        if gate not in GATES:
            raise ValueError(f"gate must be one of {', '.join(GATES)}, got {gate!r}")
        if not sigma > 0 or (gate != "none" and not threshold > 0):
            raise ValueError(f"sigma and the threshold must be > 0, got {sigma!r} and {threshold!r}")
        super().__init__(model.preset, 1)
        self.model, self.gate, self.sigma, self.threshold = model, gate, sigma, threshold

    @property
    def label(self) -> str:
        return f"{self.model.label}+lowband({self.gate},{self.sigma:g},{self.threshold:g})"

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        output, model_state = self.model.step(frame, None if state is None else state["model"])
        estimate = unjittered_resample(oidn_denoise(frame, self.preset).to(output.dtype), frame.jitter, 1)
        gate = gate_of(self.gate, self.threshold, self.sigma, frame, output, estimate)
        return low_band_corrected(output, estimate, gate, self.sigma), {"model": model_state}


def parse_variant(text: str) -> tuple[str, float, float]:
    parts = text.split(":")
    if len(parts) != 3:
        raise ValueError(f"a variant is GATE:SIGMA:THRESHOLD (e.g. stale:2:0.5), got {text!r}")
    try:
        return parts[0], float(parts[1]), float(parts[2])
    except ValueError:
        raise ValueError(f"a variant's sigma and threshold are numbers, got {text!r}") from None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a dataset with the split (data/reuse)")
    parser.add_argument("--split", default="validation")
    parser.add_argument("--model", default="fused-balanced-x1", help="a shipped 1x fused model or its checkpoint")
    parser.add_argument("--variant", action="append", metavar="GATE:SIGMA:THRESHOLD",
                        help="gate none | difference | stale, blur sigma in pixels, the gate's threshold "
                             "(repeatable; default: none:2:0, difference:4:0.02, stale:2:0.5)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--vdp", action="store_true", help="also FovVideoVDP's JOD")
    parser.add_argument("--report", type=Path, metavar="FILE.json",
                        help="where to write the JSON report (and the table as FILE.md)")
    args = parser.parse_args()
    try:
        model, _ = resolve_method(args.model, 1)
        variants = [LowBandCorrected(model, *parse_variant(text))
                    for text in args.variant or ["none:2:0", "difference:4:0.02", "stale:2:0.5"]]
        report = evaluate(args.data, [model, *variants, f"oidn-taa:{model.preset}", "oidn:high"], split=args.split,
                          scale=1, threads=args.threads, vdp=args.vdp, inference_forms="off")
    except (FileNotFoundError, ValueError, KeyError) as error:
        print(f"try_lowband_correction: {error}", file=sys.stderr)
        return 2
    table = format_table(report)
    print(table)
    if args.report:  # as `denoiser evaluate --out` writes it, with the table beside it
        args.report.write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
        args.report.with_suffix(".md").write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
