"""Step speed against output size, in fresh processes: p50 / p95 ms per frame, peak memory, GFLOP/s, OIDN's part.

    .venv/bin/python scripts/bench_resolution_scaling.py --suite fused --results docs/results
    .venv/bin/python scripts/bench_resolution_scaling.py --suite fused --model fused-fast-x1 --size 128 --frames 4
    .venv/bin/python scripts/bench_resolution_scaling.py --chart docs/resolution_scaling.png \
        --out var/results/resolution_scaling.json
    .venv/bin/python scripts/bench_resolution_scaling.py --device cuda --model munet-s-x2 --size 1920x1080

Each group of models runs at each output size in a fresh process (``model.evaluation.step_speed.time_group``):
loaded as sessions load them (inference form: the measured ``model.deployment.inference_forms`` table on the CPU,
a CUDA graph on a GPU), stepped interleaved over the same synthetic stream at the render size (the output size
over the models' scale), after warm-up frames. Without ``--suite`` each model is its own group (its memory its
own). ``--suite fused`` groups every shipped fused model with OIDN and OIDN + TAA at its quality and scale (OIDN
+ bicubic at 2x), at 128x128, 512x512 and 1080p output, the 2x models also 1080p -> 4K; rows then carry the
ratio to the same-quality OIDN, the learned part (the step less its OIDN call, timed inside it) and the check of
the inference form against the plain fp32 model. ``--results DIR`` writes JSON, Markdown and a chart named with
the device. The parent prints the table and measures the fp32 matrix-product ceiling. More: docs/benchmark.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEFAULT_MODELS = ["oidn:balanced", "oidn:high", "oidn-taa:balanced", "wskpn-s-x1", "afn-m-x1", "munet-s-x1",
                  "jnds-s-x1", "fused-balanced-x1", "oidn:balanced@2", "oidn:high@2", "oidn-taa:balanced@2",
                  "wskpn-s-x2", "afn-m-x2", "munet-s-x2", "jnds-s-x2", "jnds-s-int8-x2", "fused-balanced-x2"]
DEFAULT_SIZES = ["128", "256", "512", "1280x720", "1920x1080"]
FUSED_SIZES = ["128", "512", "1920x1080", "3840x2160"]
MAX_RENDER_PIXELS = 1920 * 1080  # the fused suite runs an output size above it only where the render stays within
# Timed frames per output size by default (more where a frame is cheap): a full fused suite on two CPU cores
# stays within minutes per size.
DEFAULT_FRAMES = ((128 * 128, 40), (512 * 512, 16), (1920 * 1080, 6), (3840 * 2160, 4))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--suite", choices=("fused",), help="fused: every shipped fused model against OIDN and "
                        "OIDN + TAA at its quality (see above)")
    parser.add_argument("--model", action="append", default=[],
                        help="pretrained name, or METHOD[:PRESET][@SCALE] (repeat; default: the shipped models and "
                             "OIDN / OIDN + TAA at both scales; with --suite fused: which fused models)")
    parser.add_argument("--size", action="append", default=[], help="output size WxH or N (repeat; default "
                        + ", ".join(DEFAULT_SIZES) + "; with --suite fused " + ", ".join(FUSED_SIZES) + ")")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"), help="where the steps run (default cpu)")
    parser.add_argument("--frames", type=int, help="timed frames (default by output size: "
                        + ", ".join(f"{frames} up to {pixels / 1e6:.2f} MP" for pixels, frames in DEFAULT_FRAMES)
                        + ")")
    parser.add_argument("--warmup", type=int, help="untimed frames first (default 2 on the CPU, 3 on CUDA: the "
                        "first frame has no history, a CUDA graph is captured on the third)")
    parser.add_argument("--check-frames", type=int, default=3,
                        help="timed frames (after the warm-up ones) on which learned models are compared with the "
                             "plain fp32 model (default 3)")
    parser.add_argument("--no-cuda-graph", action="store_true", help="on CUDA, run the steps eagerly")
    parser.add_argument("--results", type=Path, metavar="DIR",
                        help="write speed_<device>.json, .md and .png (the ratio chart) here")
    parser.add_argument("--merge", action="store_true", help="keep the rows of --results' JSON that this run "
                        "does not measure again (a quick run updates a full one)")
    parser.add_argument("--chart", type=Path, help="write the ms-per-frame chart (PNG) here")
    parser.add_argument("--out", type=Path, help="write the report (JSON) here")
    parser.add_argument("--child", nargs="+", metavar="SIZE MODEL", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.merge and not args.results:
        parser.error("--merge needs --results")
    if args.warmup is None:
        args.warmup = 3 if args.device == "cuda" else 2
    return args


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.lower().partition("x")
    return int(width), int(height or width)


def default_frames(width: int, height: int) -> int:
    return next((frames for pixels, frames in DEFAULT_FRAMES if width * height <= pixels), DEFAULT_FRAMES[-1][1])


def fused_groups(models: list[str], sizes: list[str]) -> list[tuple[str, list[str]]]:
    """(output size, models) of the fused suite: each shipped fused model (or those of ``models``) with OIDN and
    OIDN + TAA at its quality and scale, at every size whose render fits ``MAX_RENDER_PIXELS``."""
    from model.deployment.pretrained import get_pretrained, pretrained_names

    fused = [name for name in pretrained_names() if name.startswith("fused-")]
    unknown = [name for name in models if name not in fused]
    if unknown:
        raise SystemExit(f"--suite fused runs shipped fused models; not one: {', '.join(unknown)} "
                         f"(shipped: {', '.join(fused)})")
    groups = []
    for size in sizes or FUSED_SIZES:
        width, height = parse_size(size)
        for name in models or fused:
            shipped = get_pretrained(name)
            if width * height > MAX_RENDER_PIXELS * shipped.scale ** 2:
                continue
            suffix = f"@{shipped.scale}" if shipped.scale > 1 else ""
            groups.append((size, [name, f"oidn:{shipped.preset}{suffix}", f"oidn-taa:{shipped.preset}{suffix}"]))
    return groups


def load_model(model: str):
    from model.deployment.pretrained import is_pretrained, load_pretrained
    from model.methods.registry import build_method

    name, _, scale = model.partition("@")
    return (load_pretrained(name) if is_pretrained(name) else build_method(name, int(scale or 1))).eval()


def child(size: str, models: list[str], args: argparse.Namespace) -> list[dict]:
    """Time ``models`` side by side at output ``size`` in this process; their report rows."""
    import copy

    import numpy as np
    import torch

    from model.deployment.cuda_graph import with_cuda_graphs
    from model.deployment.inference_forms import load_form_table, method_key, with_inference_forms
    from model.deployment.malloc import tune_for_large_frames
    from model.evaluation.step_speed import speed_rows, time_group
    from model.io.synthetic import moving_pattern_frames
    from model.methods.base import FrameBatch
    from model.methods.oidn import oidn_device_for
    from model.methods.registry import inference_cost

    torch.set_num_threads(args.threads)
    tune_for_large_frames()  # as the sessions and the CLI run
    device = torch.device(args.device)
    table = load_form_table("measured")
    width, height = parse_size(size)
    methods, references, entries = {}, {}, []
    for model in models:
        method = load_model(model)
        _, flops_per_pixel = inference_cost(method)
        plain = method.for_inference().to(device)
        render = (width // method.scale, height // method.scale)
        if method.learned and args.check_frames:
            references[model] = copy.deepcopy(plain)
        if device.type == "cuda":
            fast = plain if args.no_cuda_graph else with_cuda_graphs(plain, device)
            form = "cuda-graph" if getattr(fast, "_cuda_graphs", None) is not None else "eager"
        else:
            fast = with_inference_forms(plain, table, device)
            form = table.form_for(method_key(method), *render).name if method_key(method) in table.keys() \
                else "eager"
        methods[model] = fast
        entries.append({"label": model, "method": method.name, "preset": method.preset, "scale": method.scale,
                        "output": [width, height], "render": list(render), "learned": bool(method.learned),
                        "form": form if method.learned else None, "flops_per_pixel": flops_per_pixel,
                        "device": device.type})
    renders = {tuple(entry["render"]) for entry in entries}
    if len(renders) != 1:
        raise SystemExit(f"a group's models must share a render size; got {sorted(renders)}")
    frames = args.frames or default_frames(width, height)
    batches = [FrameBatch.from_bundles([bundle], scale=None).to(device)
               for bundle in moving_pattern_frames(args.warmup + frames, renders.pop(), np.random.default_rng(0))]
    records = time_group(methods, batches, device, warmup=args.warmup, references=references,
                         check_frames=args.check_frames)
    rows = speed_rows(entries, records)
    for row in rows:
        row["gflops"] = row["flops_per_pixel"] * width * height / (row["p50_ms"] / 1000) / 1e9 \
            if row["flops_per_pixel"] else None
        row["oidn_device"] = oidn_device_for(device) if any(records[row["model"]].oidn_seconds) else None
        graphs = getattr(methods[row["model"]], "_cuda_graphs", None)
        if graphs is not None:  # how many structures were captured: 0 means every step ran eagerly
            row["cuda_graph_captures"] = graphs.captures
    return rows


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
            points = sorted((row["output"][0] * row["output"][1] / 1e6, row["p50_ms"]) for row in rows
                            if row["model"] == model and row["scale"] == scale)
            axis.plot(*zip(*points), marker="o", label=model.split("@")[0])
        axis.set_xscale("log")
        axis.set_yscale("log")
        axis.set_xlabel("output megapixels")
        axis.set_ylabel("p50 ms per frame")
        axis.set_title(f"{scale}x: step time against output size")
        axis.grid(True, which="both", alpha=0.3)
        axis.legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)


def groups_of(args: argparse.Namespace) -> list[tuple[str, list[str]]]:
    if args.suite == "fused":
        return fused_groups(args.model, args.size)
    return [(size, [model]) for model in args.model or DEFAULT_MODELS for size in args.size or DEFAULT_SIZES]


def run_group(size: str, models: list[str], args: argparse.Namespace) -> list[dict] | str:
    """The group's rows from a fresh process, or the last line of its error."""
    command = [sys.executable, __file__, "--child", size, *models, "--threads", str(args.threads), "--device",
               args.device, "--warmup", str(args.warmup), "--check-frames", str(args.check_frames)]
    command += ["--frames", str(args.frames)] if args.frames else []
    command += ["--no-cuda-graph"] if args.no_cuda_graph else []
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        lines = (done.stderr.strip() or done.stdout.strip() or f"exit {done.returncode}").splitlines()
        return lines[-1][:200]
    return json.loads(done.stdout.strip().splitlines()[-1])


def table_row(row: dict, ceiling: float) -> str:
    gflops = f"{row['gflops']:.1f} | {100 * row['gflops'] / ceiling:.0f}%" if row.get("gflops") else "- | -"
    ratio = f"{row['ratio_to_oidn']:.2f}" if row.get("ratio_to_oidn") is not None else "-"
    share = f"{row['learned_share']:.0%}" if row.get("learned_share") is not None else "-"
    return (f"| {row['model']} | {row['output'][0]}x{row['output'][1]} | {row['render'][0]}x{row['render'][1]} | "
            f"{row['p50_ms']:.1f} | {row['p95_ms']:.1f} | {row['peak_mb']:.0f} | {row['step_mb']:.0f} | {gflops} | "
            f"{ratio} | {share} | {row.get('oidn_device') or '-'} |")


def write_results(report: dict, folder: Path, merge: bool) -> Path:
    from model.evaluation.benchmark import save_figure
    from model.evaluation.step_speed import file_stem, markdown_table, merge_rows, ratio_figure, rounded

    stem = folder / file_stem(report["device"]["name"], report["device"]["type"], report["device"]["threads"])
    json_path = stem.with_suffix(".json")
    if merge and json_path.is_file():
        old = json.loads(json_path.read_text())
        report["rows"] = merge_rows(old["rows"], report["rows"])
        # the runs whose rows the report holds, in order
        report["commands"] = list(dict.fromkeys(old.get("commands", []) + report["commands"]))
        report["load_average"] = old.get("load_average", []) + report["load_average"]
    folder.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(rounded(report), indent=1) + "\n")
    figure = ratio_figure(report)
    chart = f"\n![ratio to OIDN]({stem.with_suffix('.png').name})\n" if figure is not None else ""
    if figure is not None:
        save_figure(figure, stem.with_suffix(".png"))
    stem.with_suffix(".md").write_text(
        f"# Step speed on {report['device']['name']}\n\n{markdown_table(report)}{chart}\n"
        "Regenerate" + (" (in order)" if len(report["commands"]) > 1 else "") + ": "
        + "<br>".join(f"`{command}`" for command in report["commands"]) + "\n")
    return json_path


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child[0], args.child[1:], args)))
        return
    import torch

    from model.evaluation.step_speed import device_name

    if args.device == "cuda" and not torch.cuda.is_available():
        raise SystemExit("--device cuda: torch sees no CUDA device here (torch.cuda.is_available() is False)")
    groups = groups_of(args)  # checked before the ceiling is measured
    load_before = os.getloadavg()[0]
    if load_before > os.cpu_count():
        print(f"warning: the load average ({load_before:.1f}) exceeds the {os.cpu_count()} cores: other processes "
              f"will slow the torch threads' parallel regions far more than OIDN's; time on a quiet machine\n")
    ceiling = sgemm_ceiling(args.threads, args.device)
    name = device_name(args.device)
    ceiling_text = f"fp32 matrix-product ceiling{' (TF32 off)' if args.device == 'cuda' else ''} {ceiling:.0f} GFLOP/s"
    print(f"{name}; {args.threads} torch threads; {ceiling_text}; peak: the most memory a step held "
          f"({'torch allocator' if args.device == 'cuda' else 'process resident set'}); step: its peak over what "
          f"was held before it; / OIDN: p50 over the same-quality OIDN's in the same process; learned: the step "
          f"less its OIDN call\n")
    print("| model | output | render | p50 ms | p95 ms | peak MB | step MB | GFLOP/s | of sgemm | / OIDN | "
          "learned share | OIDN device |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    rows = []
    for size, models in groups:
        result = run_group(size, models, args)
        if isinstance(result, str):
            print(f"| {' + '.join(models)} | {size} | failed: {result} |||||||||", flush=True)
            continue
        rows += result
        for row in result:
            print(table_row(row, ceiling), flush=True)
    report = {"format": "step-speed/1", "device": {"type": args.device, "name": name, "threads": args.threads,
                                                   "cores": os.cpu_count()},
              "load_average": [load_before, os.getloadavg()[0]],
              "torch": torch.__version__, "sgemm_gflops": ceiling, "warmup": args.warmup,
              "commands": [shlex.join([".venv/bin/python", "scripts/bench_resolution_scaling.py",
                                       *(argv if argv is not None else sys.argv[1:])])], "rows": rows}
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=1))
    if args.results and rows:
        print(f"\nreport: {write_results(report, args.results, args.merge)}")
    if args.chart and rows:
        draw(rows, args.chart)
        print(f"\nchart: {args.chart}")


if __name__ == "__main__":
    main()
