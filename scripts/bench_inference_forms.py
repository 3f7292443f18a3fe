"""Measures every inference form of each method per render resolution and writes the table the service uses.

    .venv/bin/python scripts/bench_inference_forms.py          # every shipped model; 128, 256, 512, 1080p output
    .venv/bin/python scripts/bench_inference_forms.py --model munet-s-x2 --size 256 --compile
    .venv/bin/python scripts/bench_inference_forms.py --write model/deployment/inference_forms.json

Per model (a pretrained name, or METHOD[:PRESET] with --scale) and render size, a short synthetic stream
(``model.io.synthetic``; sizes are output sizes, the table's rows are keyed by render size) is stepped in every form of
``model.deployment.inference_forms`` (rounds of all forms in turn, so a busy machine slows them alike); the first frame of each
stream is a warm-up. Printed per form: the median step (ms), the time inside the networks and what their
convolutions achieve there (GFLOP/s, and the share of this machine's ceiling measured in the same run: fp32 sgemm
for fp32 forms, bf16 gemm for bf16 ones), and the lowest PSNR of the form's output against the eager fp32 output
over the stream (display-encoded; a form is usable at ``MIN_PSNR_DB`` and above). The chosen form is the fastest
usable one, eager unless another is at least 5% faster; compiled forms are timed with ``--compile`` and chosen only
with ``--allow-compile`` (their first frame at each resolution compiles, which the table prints as ``compile s``).
``--write`` stores the table (merged into an existing one, which keeps the keys and sizes not measured now).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.deployment.inference_forms import (  # noqa: E402
    FORMS, MIN_PSNR_DB, bf16_available, form_psnr, method_key, networks_of, run_networks_as)
from model.methods.base import FrameBatch, Method  # noqa: E402
from model.methods.registry import build_method  # noqa: E402
from model.deployment.pretrained import is_pretrained, load_pretrained, pretrained_names  # noqa: E402
from model.io.synthetic import moving_pattern_frames  # noqa: E402

CHOOSE_MARGIN = 0.95  # another form must take at most 95% of eager's time to be chosen over it


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", action="append", default=[],
                        help="pretrained name or METHOD[:PRESET] (repeat; default: every shipped model)")
    parser.add_argument("--size", action="append", default=[], help="output size WxH or N (repeat; default 128, "
                                                                   "256, 512 and 1920x1080; a 2x model renders half)")
    parser.add_argument("--scale", type=int, default=1, help="scale of registry methods (default 1)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--frames", type=int, default=4, help="timed frames per stream, after one warm-up")
    parser.add_argument("--rounds", type=int, default=2, help="streams per form, interleaved (default 2)")
    parser.add_argument("--compile", action="store_true", help="also time the torch.compile forms")
    parser.add_argument("--form", action="append", default=[],
                        help="time only these forms (repeat; eager always runs, the reference)")
    parser.add_argument("--allow-compile", action="store_true", help="let the table choose compiled forms")
    parser.add_argument("--write", type=Path, help="write (merge) the measured table into this JSON file")
    parser.add_argument("--summary", type=Path, metavar="TABLE",
                        help="measure nothing: print TABLE's chosen forms per key and render size (markdown)")
    return parser.parse_args()


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    return int(width), int(height or width)


def load(name: str, scale: int) -> Method:
    method = load_pretrained(name) if is_pretrained(name) else build_method(name, scale)
    method = method.eval().for_inference()
    for parameter in method.parameters():
        parameter.requires_grad_(False)
    return method


def gemm_ceiling(dtype: torch.dtype, size: int = 2048, repeats: int = 5) -> float:
    """GFLOP/s of the best of ``repeats`` square matrix products (the machine's ceiling for that dtype)."""
    a = torch.randn(size, size).to(dtype)
    b = torch.randn(size, size).to(dtype)
    torch.mm(a, b)
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - start)
    return 2 * size ** 3 / best / 1e9


class NetworkClock:
    """Time spent inside the method's networks and the FLOPs of their convolutions (per step, summed)."""

    def __init__(self, method: Method) -> None:
        self.seconds = 0.0
        self.flops = 0
        self._started: list[float] = []
        for network in networks_of(method):
            network.register_forward_pre_hook(lambda *_: self._started.append(time.perf_counter()))
            network.register_forward_hook(self._stop)
            for module in network.modules():
                if isinstance(module, nn.Conv2d):
                    module.register_forward_hook(self._count)

    def _stop(self, *_: object) -> None:
        self.seconds += time.perf_counter() - self._started.pop()

    def _count(self, module: nn.Conv2d, _inputs: object, output: torch.Tensor) -> None:
        kh, kw = module.kernel_size
        self.flops += 2 * output.numel() * (module.in_channels // module.groups) * kh * kw

    def reset(self) -> None:
        self.seconds, self.flops = 0.0, 0


def stream(method: Method, form: str, frames: list[FrameBatch], clock: NetworkClock) -> dict:
    """Step the frames in ``form``: outputs, per-frame step seconds (warm-up excluded), network seconds and FLOPs."""
    outputs, seconds = [], []
    state = None
    network_seconds, flops = 0.0, 0
    with torch.inference_mode(), run_networks_as(method, form):
        for index, frame in enumerate(frames):
            clock.reset()
            start = time.perf_counter()
            output, state = method.step(frame, state)
            elapsed = time.perf_counter() - start
            outputs.append(output)
            if index == 0:
                first = elapsed
            else:
                seconds.append(elapsed)
                network_seconds += clock.seconds
                flops += clock.flops
    return {"outputs": outputs, "seconds": seconds, "first": first, "network_seconds": network_seconds,
            "flops": flops}


def measure(method: Method, size: tuple[int, int], forms: list[str], args: argparse.Namespace) -> dict:
    """One table row: ``size`` is the render size."""
    bundles = moving_pattern_frames(args.frames + 1, size, np.random.default_rng(0))
    frames = [FrameBatch.from_bundles([bundle], scale=None) for bundle in bundles]
    clock = NetworkClock(method)
    reference = stream(method, "eager", frames, clock)["outputs"]
    runs: dict[str, list[dict]] = {form: [] for form in forms}
    failed: dict[str, str] = {}
    compile_seconds: dict[str, float] = {}
    for form in forms:
        if FORMS[form].compiled_step:  # a stream's first two frames compile (no history, then one): not timed
            warm = stream(method, form, frames[:2], clock)
            compile_seconds[form] = warm["first"] + warm["seconds"][0]
    for _ in range(args.rounds):
        for form in forms:
            if form in failed:
                continue
            try:
                runs[form].append(stream(method, form, frames, clock))
            except Exception as error:  # noqa: BLE001 (a form this method cannot run is reported, not fatal)
                failed[form] = f"{type(error).__name__}: {str(error).splitlines()[0][:120]}"
    row: dict = {"ms": {}, "psnr_db": {}, "network_ms": {}, "conv_gflops": {}, "compile_s": {}, "failed": failed}
    for form, results in runs.items():
        if not results:
            continue
        row["ms"][form] = round(1000 * statistics.median(s for r in results for s in r["seconds"]), 3)
        row["psnr_db"][form] = round(min(form_psnr(a, b) for r in results for a, b in zip(r["outputs"], reference)), 1)
        network = sum(r["network_seconds"] for r in results)
        row["network_ms"][form] = round(1000 * network / sum(len(r["seconds"]) for r in results), 3)
        row["conv_gflops"][form] = round(sum(r["flops"] for r in results) / network / 1e9, 1) if network else 0.0
        if FORMS[form].compiled or FORMS[form].compiled_step:
            row["compile_s"][form] = round(compile_seconds.get(form, results[0]["first"]), 1)
    return row


def choose(row: dict, allow_compile: bool) -> str:
    usable = {form: ms for form, ms in row["ms"].items() if row["psnr_db"][form] >= MIN_PSNR_DB
              and (allow_compile or not FORMS[form].compiled)}
    # A compiled step stalls the first frames at each new resolution: it must beat every form without it by the margin.
    uncompiled = [ms for form, ms in usable.items() if not FORMS[form].compiled_step]
    usable = {form: ms for form, ms in usable.items()
              if not FORMS[form].compiled_step or ms <= CHOOSE_MARGIN * min(uncompiled)}
    best = min(usable, key=usable.get)
    return best if usable[best] <= CHOOSE_MARGIN * row["ms"]["eager"] else "eager"


def summary(path: Path) -> str:
    """Per key and render size: the chosen form, its speed-up over eager and its networks' conv GFLOP/s."""
    table = json.loads(path.read_text())
    measured = table.get("measured_on", {})
    ceilings = measured.get("gemm_gflops", {})
    lines = [f"measured {measured.get('date', '?')}, {measured.get('threads', '?')} torch threads, gemm ceiling "
             + ", ".join(f"{k} {v:.0f} GFLOP/s" for k, v in ceilings.items()) + "; per render size: chosen form, "
             "speed-up of the whole step over eager, the networks' conv GFLOP/s in that form (% of fp32 sgemm)", "",
             "| architecture | render size | chosen | speed-up | conv GFLOP/s (of sgemm) | lowest PSNR vs eager |",
             "|---|---|---|---:|---:|---:|"]

    def pixels(size: str) -> int:
        width, _, height = size.partition("x")
        return int(width) * int(height)

    for key in sorted(table["methods"]):
        for size in sorted(table["methods"][key], key=pixels):
            row = table["methods"][key][size]
            chosen = row["chosen"]
            gflops = row["conv_gflops"].get(chosen, 0.0)
            share = f" ({100 * gflops / ceilings['fp32']:.0f}%)" if ceilings.get("fp32") else ""
            psnr = "exact" if row["psnr_db"][chosen] >= 200 else f"{row['psnr_db'][chosen]:.0f} dB"
            lines.append(f"| `{key}` | {size} | {chosen} | {row['ms']['eager'] / row['ms'][chosen]:.2f}x | "
                         f"{gflops:.0f}{share} | {psnr} |")
    return "\n".join(lines)


def main() -> None:
    args = parse_args()
    if args.summary:
        print(summary(args.summary))
        return
    torch.set_num_threads(args.threads)
    names = args.model or pretrained_names()
    sizes = [parse_size(text) for text in args.size] or [(128, 128), (256, 256), (512, 512), (1920, 1080)]
    bf16 = bf16_available()
    forms = [name for name, form in FORMS.items()
             if (bf16 or not form.bf16) and (args.compile or not form.compiled)
             and (not args.form or name in args.form or name == "eager")]
    ceilings = {"fp32": gemm_ceiling(torch.float32)}
    if bf16:
        ceilings["bf16"] = gemm_ceiling(torch.bfloat16)
    print(f"{args.threads} torch threads, torch {torch.__version__}, {platform.processor() or platform.machine()}; "
          f"gemm ceiling: " + ", ".join(f"{k} {v:.0f} GFLOP/s" for k, v in ceilings.items()))
    print(f"ms: median step; net: time in the networks; conv: their convolutions' GFLOP/s (share of the ceiling "
          f"of the form's dtype); psnr: lowest against eager fp32 over the stream (usable >= {MIN_PSNR_DB:.0f} dB)\n")
    print("| model (key) | render size | " + " | ".join(forms) + " | chosen | speed-up |")
    print("|---|---|" + "---:|" * len(forms) + "---|---:|")
    table: dict = {"methods": {}}
    for name in names:
        method = load(name, args.scale)
        key = method_key(method)
        for output_size in sizes:
            size = (output_size[0] // method.scale, output_size[1] // method.scale)
            row = measure(method, size, forms, args)
            row["chosen"] = choose(row, args.allow_compile)
            table["methods"].setdefault(key, {})[f"{size[0]}x{size[1]}"] = row
            cells = []
            for form in forms:
                if form in row["failed"]:
                    cells.append("fails")
                    continue
                ceiling = ceilings["bf16" if FORMS[form].bf16 else "fp32"]
                gflops = row["conv_gflops"][form]
                cell = (f"{row['ms'][form]:.1f} ms (net {row['network_ms'][form]:.1f}, conv {gflops:.0f} = "
                        f"{100 * gflops / ceiling:.0f}%, {row['psnr_db'][form]:.0f} dB)")
                if form in row["compile_s"]:
                    cell += f" compile {row['compile_s'][form]:.0f} s"
                cells.append(cell)
            speedup = row["ms"]["eager"] / row["ms"][row["chosen"]]
            print(f"| {name} ({key}) | {size[0]}x{size[1]} | " + " | ".join(cells)
                  + f" | {row['chosen']} | {speedup:.2f}x |", flush=True)
            for form, error in row["failed"].items():
                print(f"    {form} fails: {error}")
    if args.write:
        merged = json.loads(args.write.read_text()) if args.write.exists() else {"methods": {}}
        for key, rows in table["methods"].items():
            merged["methods"].setdefault(key, {}).update(rows)
        merged["measured_on"] = {"processor": platform.processor() or platform.machine(), "torch": torch.__version__,
                                 "threads": args.threads, "date": datetime.date.today().isoformat(),
                                 "gemm_gflops": {k: round(v, 1) for k, v in ceilings.items()}}
        merged["allow_compile"] = args.allow_compile
        merged["min_psnr_db"] = MIN_PSNR_DB
        args.write.write_text(json.dumps(merged, indent=1, sort_keys=True) + "\n")
        print(f"\nwrote {args.write}")


if __name__ == "__main__":
    main()
