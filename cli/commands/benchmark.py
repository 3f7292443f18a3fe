"""`denoiser benchmark`: speed against accuracy for every method and preset at 1x and 2x (model/evaluation/benchmark.py)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field
from pathlib import Path

from cli.commands.evaluate import FILLED, add_run_options
from cli.main import UsageError
from cli.model_refs import MODEL_REF_PREFIX, model_checkpoint
from cli.options import add_model_options, params_from_args
from core.jobs.evaluate import baseline_methods, benchmark_scales
from core.jobs.specs import BenchmarkParams

LEARNED_RULE = """\
learned methods:
  Learned methods (WSKPN, AFN, MUNet, JNDS, ...) are benchmarked only from trained weights that you give with
  --include-learned: checkpoint files (runs/wskpn-s/best.pt), pretrained models (fused-balanced-x1) or
  registered models (models:/NAME/VERSION, models:/NAME@ALIAS, models:/NAME for the latest version, from the
  service's registry or --tracking-uri's). Their
  registry presets are never run: untrained, they would be timed and scored as if they were trained, so
  --method refuses a learned method (exit 2). A checkpoint runs at every requested scale it supports: one
  whose network works at render resolution (WSKPN, AFN) also runs at 2x as "method + bicubic" with the same
  weights; a joint denoise+upscale checkpoint (MUNet, JNDS) runs only at the scale it was trained for, and is
  listed as not run at the other.

outputs (in --out):
  benchmark.json    one row per method/preset/scale (params, FLOPs/px, PSNR, FLIP, SSIM, SMAPE, temporal
                    error, JOD, ms/frame, time / OIDN-high, Pareto flags), what was not run and why, and
                    every scale's full evaluation report
  benchmark.md      the same rows as a Markdown table, with each scale's measuring conditions
  quality_speed.png PSNR and FLIP against ms per frame (log scale), Pareto front per scale, every point
                    labelled, x1 and x2 told apart by the marker
  quality_cost.png  PSNR and FLIP against parameters and against FLOPs per output pixel
"""


def add_commands(commands) -> None:
    parser = commands.add_parser(
        "benchmark", help="speed against accuracy: every method and preset at 1x, 2x or both, table and charts",
        description="Run the evaluation protocol ('denoiser evaluate') once per output scale (--scale both: 1 and "
                    "2) on the held-out sequences of a split, for the non-learned baselines (identity, "
                    "accumulation, SVGF: every non-learned registry method), OIDN and OIDN + TAA fast / balanced / "
                    "high, and the trained models you include. "
                    "OIDN-high is timed in each run on the same frames and every row carries its time ratio "
                    "to it. Writes a JSON and a Markdown table and two charts (see below).",
        epilog=LEARNED_RULE, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset folder")
    # The benchmark job's parameters (core.jobs.specs.BenchmarkParams): names, defaults and checks as in the API.
    add_model_options(parser, BenchmarkParams, exclude=FILLED,
                      aliases={"methods": ("--method",), "oidn_timing": ("--no-oidn",)},
                      overrides={"methods": {"metavar": "NAME[:PRESET]",
                                             "help": "non-learned registry methods to run (repeatable; default: "
                                                     "every non-learned method at its default preset, and the three "
                                                     "presets of oidn and oidn-taa); see 'denoiser methods'"},
                                 "include_learned": {"metavar": "CHECKPOINT",
                                                     "help": "trained models to benchmark: checkpoint files, "
                                                             "models:/ references or pretrained models (the only "
                                                             "way learned methods are run)"},
                                 "vdp": {"help": "compute FovVideoVDP JOD (on by default, as in benchmark jobs; "
                                                 "slow on a CPU: --no-vdp skips it and the column is then '-')"}})
    parser.add_argument("--tracking-uri", default=None, metavar="URI",
                        help="MLflow store of the models:/ references; none given: the service's "
                             "(DENOISER_TRACKING_URI, else the SQLite store in DENOISER_DATA_DIR), where "
                             "'denoiser train' registers")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the table and charts")
    add_run_options(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.set_defaults(run=_run_benchmark)


# ------------------------------------------------------------------------------------------- the plan

@dataclass
class Entrant:
    """One thing to benchmark: what the model library runs (``runnable``), what the user wrote (``source``)."""

    source: str
    runnable: str
    scales: tuple[int, ...]
    learned: bool
    skipped: dict[int, str] = field(default_factory=dict)  # scale -> why it is not run there


def job_params(args) -> BenchmarkParams:
    return params_from_args(BenchmarkParams, args)


def baseline_texts(methods: list[str] | None, all_presets: bool) -> list[str]:
    """The non-learned ``NAME:PRESET`` texts to run; UsageError for a learned method, KeyError for unknown ones."""
    from model.methods.registry import method_spec, parse_method_name

    if methods is None:  # the benchmark jobs' defaults
        return baseline_methods(None, all_presets)
    texts: list[str] = []
    for text in methods:
        if text.startswith(MODEL_REF_PREFIX) or Path(text).suffix in (".pt", ".pth", ".ckpt") or "/" in text:
            raise UsageError(f"--method {text}: checkpoints and model references go to --include-learned")
        name, preset = parse_method_name(text)
        spec = method_spec(name)
        if spec.learned:
            raise UsageError(f"--method {text}: {name!r} is a learned method; its presets are untrained and "
                             f"would be benchmarked as if trained. Give trained weights with "
                             f"--include-learned CHECKPOINT or models:/NAME/VERSION")
        preset = preset or spec.default_preset
        if preset not in spec.presets:
            raise KeyError(f"method {name!r} has no preset {preset!r}; presets: {', '.join(spec.presets)}")
        presets = spec.presets if all_presets and ":" not in text else (preset,)
        texts += [f"{name}:{p}" for p in presets]
    return list(dict.fromkeys(texts))  # in order, once each


def baseline_entrants(texts: list[str], scales: tuple[int, ...]) -> list[Entrant]:
    from model.methods.registry import method_spec, parse_method_name

    entrants = []
    for text in texts:
        spec = method_spec(parse_method_name(text)[0])
        entrant = Entrant(text, text, tuple(s for s in scales if s in spec.scales), learned=False)
        entrant.skipped = {s: f"{spec.name} does not run at scale {s}" for s in scales if s not in spec.scales}
        entrants.append(entrant)
    return entrants


def learned_entrant(text: str, scales: tuple[int, ...], tracking_uri: str | None = None) -> Entrant:
    """A checkpoint file, model reference or pretrained model, with the requested scales it can run at (references
    resolve in the service's registry, or in ``tracking_uri``'s)."""
    from model.training.checkpoint import load_checkpoint
    from model.methods.registry import build_method

    path = Path(text)
    if not path.is_file():
        registry = None
        if tracking_uri is not None:
            from core.registry import registry_for
            from core.settings import get_settings

            registry = registry_for(tracking_uri, get_settings().data_dir)
        path = model_checkpoint(text, "--include-learned", registry)
        if path is None:
            raise UsageError(f"--include-learned {text}: checkpoint not found (nor a models:/ reference or "
                             f"pretrained model)")
    try:
        config = load_checkpoint(path)["method"]
        trained_scale = int(config["scale"])
        method = build_method(f"{config['method']}:{config['preset']}", scale=trained_scale)
    except (KeyError, ValueError, OSError, RuntimeError) as error:
        raise UsageError(f"--include-learned {text}: not a readable checkpoint: {error}") from None
    runs = tuple(s for s in scales if s == trained_scale or method.denoises_at_render_resolution)
    skipped = {s: f"checkpoint holds a scale-{trained_scale} {method.label}, whose network depends on its output "
                  f"scale" for s in scales if s not in runs}
    if not runs:
        raise UsageError(f"--include-learned {text}: {skipped[scales[0]]}; it cannot run at scale "
                         f"{', '.join(str(s) for s in scales)} (use --scale {trained_scale} or both)")
    return Entrant(text, str(path), runs, learned=True, skipped=skipped)


# --------------------------------------------------------------------------------------------- running

def _run_benchmark(args) -> int:
    from model.evaluation.benchmark import BENCHMARK_MARKDOWN, QUALITY_COST_CHART, QUALITY_SPEED_CHART, write_benchmark
    from core.settings import get_settings
    from model.evaluation.evaluate import TIMING_REFERENCE, evaluate, load_split

    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; give a folder")
    params = job_params(args)
    scales = benchmark_scales(params.scale)
    # Everything that can be wrong with the input is found before the first frame is run.
    for scale in scales:
        load_split(args.data, params.split, scale)
    entrants = baseline_entrants(baseline_texts(params.methods, params.all_presets), scales)
    entrants += [learned_entrant(text, scales, args.tracking_uri)
                 for text in dict.fromkeys(params.include_learned or [])]
    if not any(e.scales for e in entrants):
        raise UsageError(f"none of the methods runs at scale {params.scale}: "
                         + "; ".join(reason for e in entrants for reason in e.skipped.values()))

    reports = []
    skipped = [{"method": e.source, "scale": s, "reason": reason} for e in entrants for s, reason in e.skipped.items()]
    for scale in scales:
        running = [e for e in entrants if scale in e.scales]
        if not running:
            continue
        progress = None if args.quiet else (
            lambda message, scale=scale: print(f"[x{scale}] {message}", file=sys.stderr, flush=True))
        report = evaluate(args.data, [e.runnable for e in running], split=params.split, scale=scale,
                          frame_limit=params.frames, threads=params.threads, vdp=params.vdp,
                          timing_reference=TIMING_REFERENCE if params.oidn_timing else None,
                          device=args.device, progress=progress,
                          inference_forms=get_settings().inference_forms)
        for entry, entrant in zip(report["methods"], running):
            entry["source"] = entrant.source  # the reference as given, not the cached checkpoint's path
        reports.append(report)
    files = write_benchmark(args.out, reports, skipped)
    print(files[BENCHMARK_MARKDOWN].read_text().rstrip())
    for path in files.values():
        print(f"wrote {path}")
    missing = [name for name in (QUALITY_SPEED_CHART, QUALITY_COST_CHART) if name not in files]
    if missing:
        print(f"no chart {', '.join(missing)}: no method was both measured and scored", file=sys.stderr)
    return 0
