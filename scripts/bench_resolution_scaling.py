"""How each method's step scales from 128x128 to 1920x1080 output: ms per frame, peak memory, achieved GFLOP/s.

    .venv/bin/python scripts/bench_resolution_scaling.py --chart docs/resolution_scaling.png \
        --out var/results/resolution_scaling.json
    .venv/bin/python scripts/bench_resolution_scaling.py --model munet-s-x2 --model oidn:high --size 512 \
        --size 1920x1080
    .venv/bin/python scripts/bench_resolution_scaling.py --device cuda --out var/results/resolution_scaling_gpu.json

Every (model, output size) runs in a fresh process (so its peak memory is its own): the model is loaded as sessions
load it (inference form and the measured ``model.deployment.inference_forms`` table), a synthetic stream at the render size
(the output size over the model's scale) is stepped, the first frame as a warm-up, and the child reports the median
step, the process's peak resident memory and how much of it the steps added over the loaded model and frames,
and the FLOPs per output pixel torch counts (convolutions and matmuls; OIDN's are not visible, so it has none).
The parent measures fp32 sgemm on the same threads as the ceiling the achieved GFLOP/s are compared with, prints a
markdown table and draws ms per frame against output megapixels (log-log, one panel per scale).

With ``--device cuda`` the frames, the model and its history live on the GPU (fp32 eager: the CPU's inference-form
table does not apply), each step is timed with the device synchronized, the peak memory is the GPU's (torch's
allocator), the ceiling is a fp32 matrix product on the GPU with TF32 off, and the table says which OIDN device
denoised (OIDN's CUDA device when pyoidn has one, else its CPU device and a host round trip every frame).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_MODELS = ["oidn:balanced", "oidn:high", "oidn-taa:balanced", "wskpn-s-x1", "afn-m-x1", "munet-s-x1",
                  "jnds-s-x1", "fused-balanced-x1", "oidn:balanced@2", "oidn:high@2", "oidn-taa:balanced@2",
                  "wskpn-s-x2", "afn-m-x2", "munet-s-x2", "jnds-s-x2", "jnds-s-int8-x2", "fused-balanced-x2"]
DEFAULT_SIZES = ["128", "256", "512", "1280x720", "1920x1080"]


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", action="append", default=[],
                        help="pretrained name, or METHOD[:PRESET][@SCALE] (repeat; default: the shipped models and "
                             "OIDN / OIDN + TAA at both scales)")
    parser.add_argument("--size", action="append", default=[], help="output size WxH or N (repeat; default "
                                                                   + ", ".join(DEFAULT_SIZES) + ")")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the steps run (default cpu)")
    parser.add_argument("--frames", type=int, default=3, help="timed frames, after one warm-up (default 3)")
    parser.add_argument("--chart", type=Path, help="write the ms-per-frame chart (PNG) here")
    parser.add_argument("--out", type=Path, help="write the rows (JSON) here")
    parser.add_argument("--child", nargs=2, metavar=("MODEL", "SIZE"), help=argparse.SUPPRESS)
    return parser.parse_args()


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    return int(width), int(height or width)


def rss_mb() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2 ** 20


def child(model: str, size: str, threads: int, frames: int, device_name: str = "cpu") -> dict:
    import numpy as np
    import torch

    from model.deployment.inference_forms import load_form_table, with_inference_forms
    from model.deployment.malloc import tune_for_large_frames
    from model.methods.base import FrameBatch
    from model.methods.oidn import oidn_device_for
    from model.methods.registry import build_method, inference_cost
    from model.deployment.pretrained import is_pretrained, load_pretrained
    from model.io.synthetic import moving_pattern_frames
    from model.evaluation.timing import timed

    torch.set_num_threads(threads)
    tune_for_large_frames()  # as the sessions and the CLI run
    device = torch.device(device_name)
    name, _, scale = model.partition("@")
    method = load_pretrained(name) if is_pretrained(name) else build_method(name, int(scale or 1))
    method = method.eval()
    _, flops_per_pixel = inference_cost(method)
    method = with_inference_forms(method.for_inference().to(device), load_form_table("measured"), device)
    width, height = parse_size(size)
    render = (width // method.scale, height // method.scale)
    batches = [FrameBatch.from_bundles([bundle], scale=None).to(device)
               for bundle in moving_pattern_frames(frames + 1, render, np.random.default_rng(0))]
    before = rss_mb() if device.type == "cpu" else torch.cuda.memory_allocated(device) / 2 ** 20
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    seconds, state = [], None
    with torch.inference_mode():
        for index, batch in enumerate(batches):
            (_, state), elapsed = timed(lambda: method.step(batch, state), device)
            if index:
                seconds.append(elapsed)
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device) / 2 ** 20
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    uses_oidn = "oidn" in model or "fused" in model
    return {"model": model, "scale": method.scale, "output": [width, height], "render": list(render),
            "ms": 1000 * statistics.median(seconds), "peak_mb": peak, "step_mb": max(0.0, peak - before),
            "flops_per_pixel": flops_per_pixel, "device": device.type,
            "oidn_device": oidn_device_for(device) if uses_oidn else None}


def sgemm_ceiling(threads: int, device_name: str = "cpu", size: int = 2048) -> float:
    """fp32 matrix-product GFLOP/s, the best of five (on a GPU 8192-square with TF32 off: true fp32)."""
    import torch

    from model.evaluation.timing import timed

    torch.set_num_threads(threads)
    device = torch.device(device_name)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = False
        size = 8192
    a, b = torch.randn(size, size, device=device), torch.randn(size, size, device=device)
    torch.mm(a, b)
    best = min(timed(lambda: torch.mm(a, b), device)[1] for _ in range(5))
    return 2 * size ** 3 / best / 1e9


def draw(rows: list[dict], path: Path) -> None:
    from model.evaluation.benchmark import save_figure
    from matplotlib.figure import Figure

    scales = sorted({row["scale"] for row in rows})
    figure = Figure(figsize=(6.5 * len(scales), 5))
    for index, scale in enumerate(scales):
        axis = figure.add_subplot(1, len(scales), index + 1)
        for model in dict.fromkeys(row["model"] for row in rows if row["scale"] == scale):
            points = sorted((row["output"][0] * row["output"][1] / 1e6, row["ms"]) for row in rows
                            if row["model"] == model and row["scale"] == scale)
            axis.plot(*zip(*points), marker="o", label=model.split("@")[0])
        axis.set_xscale("log")
        axis.set_yscale("log")
        axis.set_xlabel("output megapixels")
        axis.set_ylabel("ms per frame")
        axis.set_title(f"{scale}x: step time against output size")
        axis.grid(True, which="both", alpha=0.3)
        axis.legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)


def main() -> None:
    args = parse_args()
    if args.child:
        print(json.dumps(child(*args.child, args.threads, args.frames, args.device)))
        return
    ceiling = sgemm_ceiling(args.threads, args.device)
    if args.device == "cuda":
        import torch

        print(f"{torch.cuda.get_device_name()}; fp32 matrix-product ceiling (TF32 off) {ceiling:.0f} GFLOP/s; "
              f"peak: the GPU memory torch's allocator held at most; step: what the steps added over the loaded "
              f"model and frames; OIDN: the OIDN device that denoised\n")
    else:
        print(f"{args.threads} torch threads; fp32 sgemm ceiling {ceiling:.0f} GFLOP/s; peak: the process's peak "
              f"resident memory; step: what the steps added over the loaded model and frames\n")
    print("| model | output | render | ms per frame | peak MB | step MB | GFLOP/s | of sgemm |"
          + (" OIDN |" if args.device == "cuda" else ""))
    print("|---|---|---|---:|---:|---:|---:|---:|" + ("---|" if args.device == "cuda" else ""))
    rows = []
    for model in args.model or DEFAULT_MODELS:
        for size in args.size or DEFAULT_SIZES:
            command = [sys.executable, __file__, "--child", model, size, "--threads", str(args.threads),
                       "--frames", str(args.frames), "--device", args.device]
            done = subprocess.run(command, capture_output=True, text=True)
            if done.returncode != 0:
                print(f"| {model} | {size} | failed: {done.stderr.strip().splitlines()[-1][:150]} |||||")
                continue
            row = json.loads(done.stdout.strip().splitlines()[-1])
            pixels = row["output"][0] * row["output"][1]
            row["gflops"] = row["flops_per_pixel"] * pixels / (row["ms"] / 1000) / 1e9
            rows.append(row)
            gflops = (f"{row['gflops']:.1f} | {100 * row['gflops'] / ceiling:.0f}%" if row["flops_per_pixel"]
                      else "- | -")
            print(f"| {model} | {row['output'][0]}x{row['output'][1]} | {row['render'][0]}x{row['render'][1]} | "
                  f"{row['ms']:.1f} | {row['peak_mb']:.0f} | {row['step_mb']:.0f} | {gflops} |"
                  + (f" {row['oidn_device'] or '-'} |" if args.device == "cuda" else ""), flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"threads": args.threads, "device": args.device, "sgemm_gflops": ceiling,
                                        "rows": rows}, indent=1))
    if args.chart and rows:
        draw(rows, args.chart)
        print(f"\nchart: {args.chart}")


if __name__ == "__main__":
    main()
