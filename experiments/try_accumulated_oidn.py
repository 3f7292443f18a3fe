"""Measure what OIDN gains from a running mean of the 1 spp frames instead of the single frame, with a model's own
weights (findings: docs/results/findings.md).

    .venv/bin/python experiments/try_accumulated_oidn.py --data data/reuse --split validation --model fused-fast-x1

Evaluates in one run, every method on the same frames (`model.evaluation.evaluate`, 2 threads):
- the model as given;
- `accumulated-oidn`: OIDN on a reprojected running mean of the noisy frames and their guides (up to 4 frames),
  restarted where the depth/normal test fails, faded by the stale-history test (`model.ops.stale_history`)
  where the mean is off the new frame and by the warp's blur where the camera moves;
- the same model with ``sample_mean_frames`` set (``model.methods.fused``: OIDN reads a running mean of the frames
  that keeps its samples where the network trusted its history in the frame before), saved to a temporary
  checkpoint and evaluated by its path; its weights are the model's own, not retrained for it;
- OIDN + TAA at the model's OIDN quality and OIDN-high.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.training.checkpoint import save_checkpoint  # noqa: E402
from model.evaluation.evaluate import evaluate, format_table, resolve_method  # noqa: E402
from model.methods.base import FrameBatch, Method, State, drop_history  # noqa: E402
from model.methods.fused import frame_of_sample_mean, frame_samples  # noqa: E402
from model.methods.baselines import reproject_state  # noqa: E402
from model.methods.oidn import oidn_denoise  # noqa: E402
from model.ops.sample_mean import sample_mean_spread, update_sample_mean  # noqa: E402


def accumulate_samples(frame: FrameBatch, state: State | None, max_frames: int,
                       stale_sigmas: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(running mean of the noisy frames and their guides, ``frame_samples``; frames it holds), per pixel
    (``model.ops.sample_mean``), with the history reprojected and geometry-tested as OIDN + TAA's."""
    samples = frame_samples(frame)
    if state is None:
        return samples, torch.ones_like(frame.depth)
    warped, count, valid = reproject_state(frame, state, ("samples",), 0.1, 0.9)
    return update_sample_mean(samples, warped["samples"], count, valid, max_frames, stale_sigmas,
                              spread=sample_mean_spread(frame.motion, frame.jitter, state["jitter"]))


class AccumulatedOIDN(Method):
    """OIDN (the preset is its quality) on the running mean of the noisy frames."""

    name = "accumulated-oidn"

    def __init__(self, preset: str = "fast", max_frames: int = 4, stale_sigmas: float = 2.0):
        super().__init__(preset, 1)
        self.max_frames, self.stale_sigmas = max_frames, stale_sigmas

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        samples, count = accumulate_samples(frame, drop_history(state, frame), self.max_frames, self.stale_sigmas)
        denoised = oidn_denoise(frame_of_sample_mean(frame, samples), self.preset)
        return denoised, {"samples": samples, "count": count, "depth": frame.depth, "normal": frame.normal,
                          "jitter": frame.jitter}


def with_sample_mean(model_text: str, frames: int, out: Path) -> Path:
    """The model's checkpoint with ``sample_mean_frames`` set, written to ``out`` (evaluated by its path, so the
    report tells it from the model as given)."""
    model, _ = resolve_method(model_text, 1)
    if model.name != "fused" or model.scale != 1:
        raise ValueError(f"{model_text}: needs a 1x fused model (a shipped fused-*-x1 or its checkpoint)")
    model.set_sample_mean_frames(frames)
    save_checkpoint(out, method=model)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a dataset with the split (data/reuse)")
    parser.add_argument("--split", default="validation")
    parser.add_argument("--model", default="fused-fast-x1", help="a shipped 1x fused model or its checkpoint")
    parser.add_argument("--frames", type=int, default=8, help="the sample mean's window (sample_mean_frames)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--vdp", action="store_true", help="also FovVideoVDP's JOD")
    parser.add_argument("--report", help="where to write the JSON report")
    args = parser.parse_args()
    try:
        model, _ = resolve_method(args.model, 1)
        with tempfile.TemporaryDirectory() as folder:
            variant = with_sample_mean(args.model, args.frames, Path(folder) / f"{model.name}-sample-mean.pt")
            methods = [args.model, AccumulatedOIDN(model.preset), str(variant), f"oidn-taa:{model.preset}",
                       "oidn:high"]
            report = evaluate(args.data, methods, split=args.split, scale=1, threads=args.threads, vdp=args.vdp,
                              inference_forms="off")
    except (FileNotFoundError, ValueError, KeyError) as error:
        print(f"try_accumulated_oidn: {error}", file=sys.stderr)
        return 2
    print(format_table(report))
    if args.report:
        Path(args.report).write_text(json.dumps(report, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
