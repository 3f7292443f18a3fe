"""`denoiser stability`: every method on hard scenarios and corrupted inputs; where each fails worst."""

from __future__ import annotations

import sys
from pathlib import Path

from cli.commands.evaluate import FILLED, METHODS_HELP, add_run_options
from cli.main import UsageError, positive_int, size_option
from cli.model_refs import name_sources, runnable_method
from cli.options import add_model_options, params_from_args
from core.jobs.specs import StabilityParams
from core.jobs.stability import scenario_names
from model.names import STABILITY_SCENARIOS as SCENARIOS

GENERATED_DATA = "data"  # folder inside --out that --generate renders into


def job_params(args) -> StabilityParams:
    return params_from_args(StabilityParams, args)


def add_commands(commands) -> None:
    parser = commands.add_parser(
        "stability", help="run methods on hard scenarios and corrupted inputs; report where each fails worst",
        description="Scenarios: one sequence per generator scene (moving_object, moving_light, camera_cut, "
                    "fast_camera, metals, glass, dark_fireflies, and the ghosting cases visible_emitter, "
                    "orbiting_light, sliding_over_texture), and scenarios made from one clean base sequence: "
                    "clean, first_frames (frames 0-2), exposure_bright / exposure_dark (radiance and references "
                    "x16, x1/16), nan_inf_color, nan_inf_guides, zero_motion, garbage_motion, missing_buffers. "
                    "Inputs are sanitized (NaN/Inf repaired and counted) before any method sees them; a method "
                    "that raises or returns non-finite output is recorded as failing. Writes stability.md, "
                    "stability.json and PNG charts (per-frame PSNR curves, drop heat map) into --out. A method "
                    "fails worst where its PSNR gain over the noisy input falls furthest below its median gain. "
                    "Ghosting: the error inside the region whose reference changed in the last 4 frames (from the "
                    "references and motion vectors), in every scenario that has one; lower is better.")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, metavar="DIR",
                        help="dataset folder; scene scenarios use sequences whose manifest names that scene")
    source.add_argument("--generate", action="store_true",
                        help=f"render the scenes with Mitsuba 3 into OUT/{GENERATED_DATA} first (reused when there)")
    parser.add_argument("--out", type=Path, required=True, metavar="REPORT_DIR", help="folder for the report")
    # The stability job's parameters (core.jobs.specs.StabilityParams): names, defaults and checks as in the API.
    add_model_options(parser, StabilityParams, exclude=FILLED,
                      aliases={"methods": ("--method",), "scenarios": ("--scenario",)},
                      overrides={"methods": {"metavar": "METHOD", "help": METHODS_HELP},
                                 "scenarios": {"metavar": "NAME", "help": "run only these scenarios (repeatable; "
                                               "default: all). One of: " + ", ".join(SCENARIOS)},
                                 "base": {"metavar": "SEQUENCE"},
                                 "frames": {"help": "with --data: use the first N frames of each sequence (default: "
                                                    "all); with --generate: frames to render (default: 8)"},
                                 "seed": {"help": "seeds the corruptions; with --generate, also the scenes"}})
    parser.add_argument("--size", type=size_option, default=(64, 64), metavar="N|WxH",
                        help="--generate: render resolution (default: 64)")
    parser.add_argument("--ref-spp", type=positive_int, default=64, metavar="N",
                        help="--generate: samples per pixel of the references (default: 64)")
    parser.add_argument("--variant", choices=("llvm_ad_rgb", "cuda_ad_rgb", "scalar_rgb"), default=None,
                        help="--generate: Mitsuba variant (default: the fastest available)")
    add_run_options(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.set_defaults(run=_run_stability)


def _run_stability(args) -> int:
    from model.evaluation.stability import build_scenarios, generate_scenarios, run_suite
    from model.evaluation.stability_report import write_report

    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; give a folder for the report")
    if not args.generate:
        for option, default, value in (("--size", (64, 64), args.size), ("--ref-spp", 64, args.ref_spp),
                                       ("--variant", None, args.variant)):
            if value != default:
                raise UsageError(f"{option} applies to --generate only")
    params = job_params(args)
    names = scenario_names(params)
    methods = [runnable_method(text, "--method") for text in params.methods]
    say = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    data = args.data
    frame_limit = params.frames
    if args.generate:
        data = generate_scenarios(args.out / GENERATED_DATA, size=args.size, frames=params.frames or 8,
                                  ref_spp=args.ref_spp, scale=params.scale, seed=params.seed, names=names,
                                  variant=args.variant, progress=say)
        frame_limit = None
    scenarios, missing = build_scenarios(data, params.scale, names=names, base=params.base,
                                         frame_limit=frame_limit, seed=params.seed)
    for entry in missing:
        say(f"skipping {entry['name']}: {entry['reason']}")
    if not scenarios:
        raise UsageError(f"none of the scenarios can be built from {data}: "
                         + "; ".join(f"{m['name']}: {m['reason']}" for m in missing))
    report = run_suite(scenarios, [runnable for runnable, _ in methods], params.scale, vdp=params.vdp,
                       device=args.device, threads=params.threads, progress=say, missing=missing, data=str(data))
    name_sources(report["methods"], methods)
    files = write_report(report, args.out)
    for entry in report["methods"]:
        worst = entry["worst"]
        if worst["scenario"] is None:
            what = "no scenario below its median"
        elif worst["failed"]:
            what = f"{worst['scenario']} (FAILED: {worst['reason']})"
        else:
            what = f"{worst['scenario']} ({worst['drop_db']:.2f} dB below its median gain)"
        print(f"{entry['label']}: fails worst on {what}")
    ghosting = report["ghosting"]
    if ghosting["least"] is not None:
        print(f"ghosts least among temporal methods: {ghosting['least']} (mean ghost error "
              f"{ghosting['mean_error'][ghosting['least']]:.4f} over {len(ghosting['common_scenarios'])} scenarios)")
    print(f"wrote {files['markdown']}, {files['json'].name} and charts in {args.out}")
    return 0
