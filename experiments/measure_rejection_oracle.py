"""How far a perfect stale-history test could take a 1x fused model: its output with its own OIDN estimate put in
wherever the reference changed from the frame before (findings: docs/results/findings.md).

    .venv/bin/python experiments/measure_rejection_oracle.py --data data/reuse --split test --sequence moving_light_s4 \
        --model fused-fast-x1 --model fused-balanced-x1 --model fused-high-x1 --out var/results/rejection_oracle.json

A stale-history test can do no better than to send a model to its spatial estimate exactly where the scene changed;
the oracle knows where from the references, which no method sees. Per model and sequence it reports the model, its
estimate alone (OIDN at the model's quality, read at the pixel centres as the 1x models read it) and the oracle at
each threshold of change (the luminance change to the frame before over their sum, a 5 x 5 mean of it; all of a
frame after a camera cut, none of the first frame), with the share of pixels the oracle replaced. PSNR and the
temporal error as ``denoiser evaluate`` computes them; FovVideoVDP's JOD unless --no-vdp.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.evaluation.evaluate import EvaluationSequence, load_split, resolve_method, run_sequence  # noqa: E402
from model.methods.fused import unjittered_resample  # noqa: E402
from model.methods.oidn import oidn_denoise  # noqa: E402
from model.methods.oidn_taa import reinhard, reinhard_inverse  # noqa: E402
from model.evaluation.metrics import FovVideoVdp, psnr, temporal_error  # noqa: E402
from model.ops.box_filter import replicated_box_mean  # noqa: E402
from model.ops.tonemap import display_encode  # noqa: E402
from model.io.sanitize import sanitize_frame  # noqa: E402
from model.evaluation.timing import torch_threads  # noqa: E402

CHANGE_WINDOW = 5  # the change is averaged over this many pixels a side, so a region changes, not single pixels
CHANGE_OFFSET = 0.02  # keeps the relative change of two dark pixels small


def changed_share(references: torch.Tensor, camera_cuts: list[bool]) -> torch.Tensor:
    """(T, 1, H, W): each pixel's luminance change from the frame before over the two luminances' sum (+ an offset),
    a ``CHANGE_WINDOW`` mean of it; 0 on the first frame and 1 on a frame after a camera cut."""
    luminance = references.mean(dim=1, keepdim=True)
    change = torch.zeros_like(luminance)
    change[1:] = (luminance[1:] - luminance[:-1]).abs() / (luminance[1:] + luminance[:-1] + CHANGE_OFFSET)
    change = replicated_box_mean(change, CHANGE_WINDOW)
    for index, cut in enumerate(camera_cuts):
        if cut and index > 0:
            change[index] = 1.0
    return change


def oracle(output: torch.Tensor, estimate: torch.Tensor, change: torch.Tensor, threshold: float) -> torch.Tensor:
    """The output with the estimate wherever the change is past ``threshold``."""
    return torch.where(change > threshold, estimate, output)


def estimates(sequence: EvaluationSequence, quality: str) -> torch.Tensor:
    """OIDN's estimate of every frame, read at the pixel centres as the 1x fused models read it (T, 3, H, W)."""
    read = []
    with torch.inference_mode():
        for frame in sequence.frames:
            inputs, _ = sanitize_frame(frame.without_reference())
            mapped = reinhard(oidn_denoise(inputs, quality).to(inputs.color.dtype))
            read.append(reinhard_inverse(unjittered_resample(mapped, inputs.jitter, 1))[0])
    return torch.stack(read)


def scores(outputs: torch.Tensor, references: torch.Tensor, cuts: list[bool], vdp: FovVideoVdp | None) -> dict:
    encoded, reference = display_encode(outputs), display_encode(references)
    return {"psnr": statistics.fmean(psnr(encoded, reference).tolist()),
            "temporal_error": temporal_error(encoded, reference, cuts),
            "fvvdp_jod": vdp.jod(encoded, reference) if vdp is not None else None}


def measure(data: Path, split: str, models: list[str], thresholds: list[float], names: list[str] | None,
            vdp: FovVideoVdp | None) -> list[dict]:
    sequences = [EvaluationSequence.from_sequence(s, 1) for s in load_split(data, split, 1)]
    if names:
        missing = sorted(set(names) - {s.name for s in sequences})
        if missing:
            raise ValueError(f"no sequence {', '.join(missing)} in the {split} split of {data}")
        sequences = [s for s in sequences if s.name in names]
    methods = [resolve_method(text, 1)[0] for text in models]
    for text, method in zip(models, methods):
        if method.name != "fused" or method.scale != 1:
            raise ValueError(f"{text}: needs a 1x fused model (a shipped fused-*-x1 or its checkpoint)")
    rows = []
    for sequence in sequences:
        references = torch.cat([frame.reference for frame in sequence.frames])
        cuts = sequence.camera_cuts
        change = changed_share(references, cuts)
        for text, method in zip(models, methods):
            outputs = run_sequence(method.for_inference(), sequence, keep_outputs=True)["outputs"]
            estimate = estimates(sequence, method.preset)
            row = {"sequence": sequence.name, "model": text, "quality": method.preset,
                   "model_scores": scores(outputs, references, cuts, vdp),
                   "estimate_scores": scores(estimate, references, cuts, vdp), "oracle": []}
            for threshold in thresholds:
                row["oracle"].append({"threshold": threshold, "share": float((change > threshold).float().mean()),
                                      **scores(oracle(outputs, estimate, change, threshold), references, cuts, vdp)})
            rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    def cell(values: dict) -> str:
        jod = values["fvvdp_jod"]
        return f"{values['psnr']:.2f} / " + ("-" if jod is None else f"{jod:.2f}")

    thresholds = [entry["threshold"] for entry in rows[0]["oracle"]] if rows else []
    lines = ["| sequence | model | model | its estimate | " + " | ".join(f"oracle, change > {t:g}" for t in thresholds)
             + " |", "|---|---|---:|---:|" + "---:|" * len(thresholds)]
    for row in rows:
        oracles = [f"{cell(entry)} ({entry['share']:.0%})" for entry in row["oracle"]]
        lines.append(f"| {row['sequence']} | {row['model']} | {cell(row['model_scores'])} | "
                     f"{cell(row['estimate_scores'])} | " + " | ".join(oracles) + " |")
    return "PSNR dB / JOD (share of pixels the oracle replaced)\n\n" + "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a dataset with 1x references (data/reuse)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--model", action="append", required=True, help="a 1x fused model (repeatable)")
    parser.add_argument("--sequence", action="append", help="only these sequences (repeatable; default: all)")
    parser.add_argument("--threshold", type=float, action="append",
                        help="a change threshold (repeatable; default: 0.02, 0.05, 0.1)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-vdp", action="store_true", help="skip FovVideoVDP")
    parser.add_argument("--out", type=Path, help="where to write the JSON report (and the table as .md)")
    args = parser.parse_args()
    try:
        vdp = None if args.no_vdp else FovVideoVdp()
        if vdp is not None and not vdp.available:
            raise ValueError(vdp.unavailable_reason)
        with torch_threads(args.threads):
            rows = measure(args.data, args.split, args.model, args.threshold or [0.02, 0.05, 0.1], args.sequence,
                           vdp)
    except (FileNotFoundError, ValueError, KeyError) as error:
        print(f"measure_rejection_oracle: {error}", file=sys.stderr)
        return 2
    text = table(rows)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"data": str(args.data), "split": args.split, "rows": rows}, indent=2,
                                       allow_nan=False) + "\n")
        args.out.with_suffix(".md").write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
