"""Held-out quality of a model's fast inference form against its plain fp32 eager form, on one dataset.

    .venv/bin/python scripts/compare_fast_forms.py --data var/fast_fused/heldout --model fused-balanced-x1 \
        --model fused-fast-x1 --form compile-step+bf16 --form measured --out var/results/fast_forms_quality.json

Each model is evaluated (``model.evaluation.evaluate``, no FovVideoVDP, no OIDN timing) once as the plain model
runs it, every network and step eager in fp32 on torch's ops (the table "off", the native kernels off), and once per
``--form`` with the native kernels (``model.ops.native``): a form name runs that form at every resolution, ``off``
fp32 eager, ``measured`` the shipped table's choice per resolution (what sessions run). Prints per model and form the
mean display PSNR and SSIM over the split's sequences, the difference to the plain model in dB, and the lowest
per-sequence difference.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="dataset folder")
    parser.add_argument("--split", default="test")
    parser.add_argument("--scale", type=int, default=1)
    parser.add_argument("--model", action="append", required=True, help="pretrained model (repeat)")
    parser.add_argument("--form", action="append", default=[], help="form name or 'measured' (repeat)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, help="write the rows (JSON) here")
    return parser.parse_args()


def forced_table(key: str, form: str):
    """A table whose one row runs ``form`` at every resolution."""
    from model.deployment.inference_forms import FormTable

    return FormTable({"methods": {key: {"128x128": {"chosen": form, "ms": {form: 1.0, "eager": 2.0},
                                                    "psnr_db": {form: 200.0, "eager": 200.0}}}}},
                     allow_compile=True)


def main() -> None:
    args = parse_args()
    from model.deployment.inference_forms import method_key
    from model.deployment.pretrained import load_pretrained
    from model.evaluation.evaluate import evaluate
    from model.ops import native

    rows = []
    print("| model | form | PSNR dB | SSIM | PSNR - plain model | lowest per-sequence difference |")
    print("|---|---|---:|---:|---:|---:|")
    for name in args.model:
        key = method_key(load_pretrained(name))
        per_form = {}
        for index, form in enumerate(["plain", *(args.form or ["measured"])]):
            table = "off" if form == "plain" else form if form in ("off", "measured") else forced_table(key, form)
            native.set_enabled(index > 0)
            report = evaluate(args.data, [load_pretrained(name)], args.split, args.scale, threads=args.threads,
                              vdp=False, timing_reference=None, inference_forms=table)
            native.set_enabled(True)
            entry = report["methods"][0]
            per_form[form] = {sequence: values["psnr"] for sequence, values in entry["sequences"].items()}
            psnr, ssim = entry["metrics"]["psnr"], entry["metrics"]["ssim"]
            difference = 0.0 if form == "plain" else psnr - next(
                r["psnr"] for r in rows if r["model"] == name and r["form"] == "plain")
            lowest = min(per_form[form][s] - per_form["plain"][s] for s in per_form[form])
            rows.append({"model": name, "form": form, "psnr": psnr, "ssim": ssim, "psnr_delta_db": difference,
                         "lowest_sequence_delta_db": lowest})
            label = {"plain": "fp32 eager, torch ops", "off": "fp32 eager, native kernels"}.get(
                form, f"{form}, native kernels")
            print(f"| {name} | {label} | {psnr:.3f} | {ssim:.4f} | "
                  f"{difference:+.4f} | {lowest:+.4f} |", flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
