"""Measure the output bound on shipped models: worst output / input ratio and PSNR, with and without the bound.

Each model steps every test sequence of DATA (at the model's scale) and stability scenarios derived from the first
of them (model.evaluation.stability.derive_scenarios), once through its bounded ``step`` and once through
``model.methods.base.unbounded_step``, each with its own history. Per model and sequence it reports the worst
frame's brightest-output / brightest-input ratio, the display PSNR (model.evaluation.metrics.psnr) and the
relative squared error in linear HDR, both ways, and the references' own worst ratio (what the bound must allow).

    python scripts/measure_output_bounds.py --data DATA --out docs/results/output_bounds.md [--models NAME ...]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.deployment.pretrained import is_pretrained, load_pretrained, pretrained_names  # noqa: E402
from model.evaluation.evaluate import EvaluationSequence, load_split  # noqa: E402
from model.evaluation.metrics import psnr  # noqa: E402
from model.evaluation.stability import derive_scenarios  # noqa: E402
from model.io.sanitize import sanitize_frame  # noqa: E402
from model.methods.base import unbounded_step  # noqa: E402
from model.methods.registry import build_method  # noqa: E402
from model.ops.output_bound import OUTPUT_BOUND_FACTOR, OUTPUT_BOUND_FLOOR, output_ratio  # noqa: E402
from model.ops.tonemap import display_encode  # noqa: E402

DERIVED = ("exposure_bright", "nan_inf_color")


def measure(method, sequence: EvaluationSequence) -> dict:
    """Worst ratio and mean PSNR over the sequence, bounded and unbounded."""
    result = {}
    for label, step in (("bounded", lambda f, s: method.step(f, s)), ("unbounded", lambda f, s: unbounded_step(method, f, s))):
        state, ratios, values, errors, references = None, [], [], [], []
        with torch.inference_mode():
            for frame in sequence.frames:
                inputs, _ = sanitize_frame(frame.without_reference())
                output, state = step(inputs, state)
                ratios.append(output_ratio(output, inputs.color))
                finite = torch.nan_to_num(output, nan=0.0, posinf=0.0, neginf=0.0)  # PSNR of what a display shows
                values.append(float(psnr(display_encode(finite), display_encode(frame.reference))[0]))
                # Display PSNR cannot see radiance above 1; the relative squared error in linear HDR can.
                errors.append(float(((finite - frame.reference) ** 2 / (frame.reference ** 2 + 0.01)).mean()))
                references.append(output_ratio(frame.reference, inputs.color))
        result[label] = {"ratio": max(ratios), "psnr": statistics.fmean(values), "relmse": statistics.fmean(errors)}
    result["reference_ratio"] = max(references)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--out", required=True)
    parser.add_argument("--models", nargs="*", default=None, help="shipped model names or NAME[:PRESET] methods at 1x (default: every shipped model)")
    args = parser.parse_args()
    torch.manual_seed(0)
    rows = []
    for name in args.models or pretrained_names():
        method = load_pretrained(name) if is_pretrained(name) else build_method(name).eval()
        sequences = [EvaluationSequence.from_sequence(s, method.scale) for s in load_split(args.data, "test", method.scale)]
        sequences += [s.sequence for s in derive_scenarios(sequences[0], DERIVED)]
        names = [s.name for s in sequences[:-len(DERIVED)]] + list(DERIVED)
        for label, sequence in zip(names, sequences):
            measured = measure(method, sequence)
            rows.append((name, label, measured))
            print(name, label, measured, flush=True)
    lines = ["| model | sequence | reference / input | worst output / input, unbounded | bounded "
             "| PSNR unbounded (dB) | PSNR bounded (dB) | relMSE unbounded | relMSE bounded |",
             "|---|---|--:|--:|--:|--:|--:|--:|--:|"]
    for name, label, m in rows:
        u, b = m["unbounded"], m["bounded"]
        lines.append(f"| {name} | {label} | {m['reference_ratio']:.3g} | {u['ratio']:.3g} | {b['ratio']:.3g} "
                     f"| {u['psnr']:.3f} | {b['psnr']:.3f} | {u['relmse']:.4g} | {b['relmse']:.4g} |")
    Path(args.out).write_text("\n".join(lines) + "\n")
    print(f"factor {OUTPUT_BOUND_FACTOR:g}, floor {OUTPUT_BOUND_FLOOR:g}; table written to {args.out}")


if __name__ == "__main__":
    main()
