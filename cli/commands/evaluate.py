"""`denoiser evaluate` and `denoiser methods`: the benchmark protocol on a dataset, and what can be evaluated."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from cli.main import UsageError, device_option
from cli.model_refs import name_sources, runnable_method
from cli.options import add_model_options, params_from_args
from core.jobs.specs import EvaluateParams

# Fields of the evaluate job's parameters the command fills itself (the parity test lists them too): a local
# run reads the dataset folder --data and writes files, it does not log to MLflow.
FILLED = ("dataset", "track")
METHODS_HELP = ("method from the registry (see 'denoiser methods'), a pretrained model, a models:/ reference or a "
                "checkpoint file; repeat for several")


def add_run_options(parser) -> None:
    """The local-only options of how methods are run, shared by evaluate, benchmark and stability."""
    parser.add_argument("--device", type=device_option, default="cpu",
                        help="torch device the methods run on: cpu (default), cuda, cuda:1")


def job_params(args) -> EvaluateParams:
    return params_from_args(EvaluateParams, args)


def add_commands(commands) -> None:
    _add_evaluate(commands)
    _add_compare(commands)
    _add_methods(commands)


# ------------------------------------------------------------------------------------------- evaluate

def _add_evaluate(commands) -> None:
    parser = commands.add_parser(
        "evaluate", help="score and time methods on whole sequences of a dataset split (the benchmark protocol)",
        description="Run each method frame by frame over every sequence of a split, its history carried and "
                    "camera cuts honoured. Quality: PSNR, SSIM and FLIP on display-encoded frames "
                    "(clip(x,0,1)^(1/2.2)), SMAPE on linear HDR, the temporal error and FovVideoVDP JOD per "
                    "sequence. Speed: median wall time of a step after 2 warm-up frames per sequence, with its "
                    "ratio to OIDN-high timed in the same run on the same frames. Prints a Markdown table.")
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset folder")
    # The evaluate job's parameters (core.jobs.specs.EvaluateParams): names, defaults and checks as in the API.
    add_model_options(parser, EvaluateParams, exclude=FILLED,
                      aliases={"methods": ("--method", "--model"), "oidn_timing": ("--no-oidn",)},
                      overrides={"methods": {"metavar": "METHOD", "help": METHODS_HELP}})
    parser.add_argument("--out", type=Path, default=None, metavar="FILE.json", help="write the full report here")
    add_run_options(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.set_defaults(run=_run_evaluate)


def _run_evaluate(args) -> int:
    from core.settings import get_settings
    from model.evaluation.evaluate import TIMING_REFERENCE, evaluate, format_table

    if args.out is not None and args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder; give a file name such as report.json")
    params = job_params(args)
    progress = None if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    methods = [runnable_method(text, "--method") for text in params.methods]
    report = evaluate(args.data, [runnable for runnable, _ in methods], split=params.split, scale=params.scale,
                      frame_limit=params.frames, threads=params.threads, vdp=params.vdp,
                      timing_reference=TIMING_REFERENCE if params.oidn_timing else None,
                      device=args.device, progress=progress, inference_forms=get_settings().inference_forms)
    name_sources(report["methods"], methods)
    print(format_table(report))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
        print(f"wrote {args.out}")
    return 0


# -------------------------------------------------------------------------------------------- compare

def _add_compare(commands) -> None:
    parser = commands.add_parser(
        "compare", help="picture of one frame: input upscaled, each method's output, reference (PNG)",
        description="Step each method through a sequence of the dataset up to frame INDEX (history carried, as "
                    "in evaluation) and draw one row: the 1spp input (bicubic-upscaled at scale 2), every "
                    "method's output at that frame with its PSNR and FLIP, and the reference. --zoom adds a row "
                    "of enlarged crops.")
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset folder")
    parser.add_argument("--sequence", required=True, metavar="NAME", help="sequence of the dataset")
    parser.add_argument("--frame", type=int, default=-1, metavar="INDEX",
                        help="frame to show; negative counts from the end (default: -1, the last)")
    parser.add_argument("--method", "--model", action="append", required=True, metavar="MODEL[=LABEL]",
                        help="method, pretrained model, models:/ reference or checkpoint as for 'denoiser "
                             "evaluate', optionally with a panel label after '='; repeat for several")
    parser.add_argument("--scale", type=int, choices=(1, 2), default=1, help="output / render resolution ratio")
    parser.add_argument("--zoom", type=_zoom_option, default=None, metavar="X,Y,SIZE",
                        help="also show the square at output pixel (X, Y) with side SIZE, enlarged")
    parser.add_argument("--device", type=device_option, default="cpu",
                        help="torch device the methods run on")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.png", help="picture to write")
    parser.set_defaults(run=_run_compare)


def _zoom_option(text: str) -> tuple[int, int, int]:
    import argparse

    try:
        x, y, size = (int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"zoom must be X,Y,SIZE (three integers), got {text!r}") from None
    if x < 0 or y < 0 or size < 2:
        raise argparse.ArgumentTypeError(f"zoom needs X, Y >= 0 and SIZE >= 2, got {text!r}")
    return x, y, size


def _run_compare(args) -> int:
    from model.evaluation.compare import comparison_panels, save_comparison
    from model.io.dataset import Dataset

    dataset = Dataset(args.data)
    if args.sequence not in dataset.names():
        raise UsageError(f"dataset {args.data} has no sequence {args.sequence!r}; it has: "
                         f"{', '.join(dataset.names()) or 'none'}")
    sequence = dataset.sequence(args.sequence)
    index = args.frame if args.frame >= 0 else len(sequence) + args.frame
    if not 0 <= index < len(sequence):
        raise UsageError(f"--frame {args.frame}: sequence {sequence.name!r} has {len(sequence)} frames (0 to "
                         f"{len(sequence) - 1}, or -1 to -{len(sequence)} from the end)")
    methods, labels = [], []
    for text in args.method:
        method, _, label = text.partition("=")
        methods.append(runnable_method(method, "--method")[0])
        labels.append(label or None)
    panels = comparison_panels(sequence, methods, index, args.scale, labels, device=args.device)
    title = f"{sequence.name}, frame {index}: {sequence[index].width}x{sequence[index].height} -> x{args.scale}"
    out = save_comparison(panels, args.out, title=title, zoom=args.zoom)
    for panel in panels[1:-1]:
        print(f"{panel.title}: PSNR {panel.psnr:.2f} dB, FLIP {panel.flip:.4f}")
    print(f"wrote {out}")
    return 0


# -------------------------------------------------------------------------------------------- methods

def _add_methods(commands) -> None:
    parser = commands.add_parser(
        "methods", help="list every registered method and preset with its parameters and FLOPs per pixel",
        description="One row per method and preset: output scales, whether it is learned, parameter count and "
                    "FLOPs per output pixel of one step with history (torch's FLOP counter: convolutions and "
                    "matmuls; element-wise ops and OIDN's own network are not counted).")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(run=_run_methods)


def _method_rows() -> list[dict]:
    from model.methods import registry

    rows = []
    for spec in registry.all_methods():
        scale = 1 if 1 in spec.scales else spec.scales[0]
        for preset in spec.presets:
            params_count, flops = registry.inference_cost(spec.factory(preset, scale))
            rows.append({"method": spec.name, "preset": preset, "default": preset == spec.default_preset,
                         "scales": list(spec.scales), "learned": spec.learned,
                         "params": params_count, "flops_per_pixel": flops,
                         "description": spec.description})
    return rows


def _run_methods(args) -> int:
    rows = _method_rows()
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    header = ("method", "scales", "learned", "params", "FLOPs/px", "description")
    table = [header]
    for row in rows:
        name = row["method"] if row["preset"] == "default" else f"{row['method']}:{row['preset']}"
        name += " *" if row["default"] and row["preset"] != "default" else ""
        table.append((name, ",".join(str(s) for s in row["scales"]), "yes" if row["learned"] else "no",
                      f"{row['params']:,}", f"{row['flops_per_pixel']:,.0f}", row["description"]))
    widths = [max(len(line[column]) for line in table) for column in range(len(header))]
    numeric = {3, 4}
    for line in table:
        cells = (cell.rjust(w) if c in numeric else cell.ljust(w) for c, (cell, w) in enumerate(zip(line, widths)))
        print("  ".join(cells).rstrip())
    if any(row["default"] and row["preset"] != "default" for row in rows):
        print("* default preset (NAME alone means NAME:DEFAULT)")
    return 0
