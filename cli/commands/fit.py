"""`denoiser fit`: right-sizing, the smallest preset of a learned family that meets a target (model.fit)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from cli.main import HelpFormatter, EXIT_FAILURE, UsageError, registered_name, size_list
from cli.options import add_model_options, params_from_args
from core.jobs.specs import FitParams
from model.names import TRAIN_DEVICES
from model.training.training_settings import FitTrainingSettings



def add_commands(commands) -> None:
    parser = commands.add_parser(
        "fit", help="train a ladder of a family's presets and register the smallest that meets a target",
        description="Right-sizing. Orders the presets of a learned family by FLOPs per pixel, times each one "
                    "(ms per frame on synthetic frames of the stated render size, median after warm-up), trains "
                    "(or reuses) and measures on the validation split (PSNR, SSIM, FLIP) only the presets the "
                    "target needs, and registers the smallest that meets it with an alias. Targets: psnr=DB "
                    "(validation PSNR >= DB), flip=E (validation FLIP <= E), ms=MS[@WxH] (ms per frame <= MS at "
                    "render size WxH, then the best PSNR among those), within=DB (PSNR within DB of the largest "
                    "preset). A preset already trained with the same settings on the same data (a checkpoint "
                    "under OUT, or a registered version with the same fit key) is reused. Prints the ladder table; "
                    "writes OUT/ladder.json and OUT/ladder.md; logs one MLflow run with the ladder.",
        formatter_class=HelpFormatter)
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset folder")
    # The fit job's parameters (core.jobs.specs.FitParams: the training options of every preset are the fields of
    # model.training.training_settings.FitTrainingSettings), but the dataset id, which is --data here.
    add_model_options(parser, FitParams, exclude=("dataset",), exclusive=[("steps", "epochs")],
                      aliases={"warmup_steps": ("--warmup",), "track": ("--no-tracking",)},
                      overrides={"method": {"metavar": "FAMILY"},
                                 "presets": {"metavar": "P1,P2,..."},
                                 "target": {"metavar": "psnr=DB|flip=E|ms=MS[@WxH]|within=DB"},
                                 "time_at": {"type": size_list, "metavar": "WxH", "shown_default": "256x256",
                                             "help": "render resolution the presets are timed at (WxH or N for "
                                                     "NxN); an ms target's own @WxH takes precedence"},
                                 "register_as": {"type": registered_name, "metavar": "NAME",
                                                 "help": "registered model of the ladder's versions (default: "
                                                         "FAMILY-fit-xSCALE)"},
                                 "validation_split": {"help": "split the presets are measured on (must not be "
                                                              "empty)"},
                                 "track": {"help": "log to MLflow, register versions and set the alias (no: "
                                                   "nothing registered or aliased, no registry reuse; checkpoints "
                                                   "under OUT are still reused)"}})
    parser.add_argument("--device", choices=TRAIN_DEVICES, default="auto",
                        help="where presets train, run and are timed")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="presets train into DIR/PRESET-KEY/ (default: runs/fit-FAMILY-xSCALE in the data "
                             "folder, DENOISER_DATA_DIR)")
    parser.add_argument("--tracking-uri", default=None, metavar="URI",
                        help="MLflow tracking URI (default: the service's: DENOISER_TRACKING_URI, else the SQLite "
                             "store in DENOISER_DATA_DIR)")
    parser.add_argument("--json", type=Path, default=None, metavar="FILE", help="also write the ladder JSON here")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.set_defaults(run=_run_fit)


def job_params(args) -> FitParams:
    return params_from_args(FitParams, args)


def _run_fit(args) -> int:
    from model.fit.plan import FitConfig, plan_fit
    from model.fit.report import format_ladder
    from model.fit.runner import fit
    from core.storage import get_storage

    params = job_params(args)
    family = params.method
    training = FitTrainingSettings(**params.model_dump(include=set(FitTrainingSettings.model_fields)))
    config = FitConfig(
        **training.model_dump(), family=family, data=str(args.data), target=params.target,
        presets=params.presets, time_at=tuple(params.time_at), timing_frames=params.timing_frames,
        # No --out: the data folder's runs/, not the current folder, so a rerun from anywhere reuses its presets.
        device=args.device, out=str(args.out or get_storage().runs / f"fit-{family}-x{training.scale}"),
        alias=params.alias,
        tracking_uri=args.tracking_uri)
    if args.json is not None and args.json.is_dir():
        raise UsageError(f"--json {args.json} is a folder; give a file name such as ladder.json")
    plan = plan_fit(config)  # every input problem surfaces here (exit status 2), before anything trains

    say = (lambda message: None) if args.quiet else (lambda message: print(message, file=sys.stderr, flush=True))
    progress = None if args.quiet else _StepPrinter()
    recorder = None
    if params.track:
        from core.fit_tracking import start_fit_run

        recorder = start_fit_run(config, args.tracking_uri, f"fit {family} {plan.target}")
    try:
        result = fit(config, store=recorder, tracker=recorder,
                     train_tracker=recorder.train_tracker if recorder else None, progress=progress, say=say,
                     plan=plan)
    except BaseException as error:
        if recorder is not None:
            recorder.finish("KILLED" if isinstance(error, KeyboardInterrupt) else "FAILED")
        raise
    if recorder is not None:
        recorder.finish("FINISHED")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result.to_dict(), indent=2) + "\n")
    print(format_ladder(result))
    print(f"ladder: {Path(config.out) / 'ladder.json'}" + (f", MLflow run {recorder.run_id}" if recorder else ""))
    if not result.met:
        print(f"denoiser fit: no preset meets the target: {result.reason}", file=sys.stderr)
        return EXIT_FAILURE
    return 0


class _StepPrinter:
    """Training progress on stderr: one line every tenth of a preset's steps, and its last."""

    def __init__(self) -> None:
        self.last = None

    def __call__(self, current: int, total: int, message: str) -> None:
        # Other stages (timing, measuring, the choice) are reported by the fit's own lines.
        if message == self.last or ": step " not in message:
            return
        self.last = message
        _, _, rest = message.partition(": step ")
        try:
            step, steps = (int(v) for v in rest.split(",", 1)[0].split("/"))
        except ValueError:
            return
        if step == steps or step % max(1, steps // 10) == 0:
            print(message, file=sys.stderr, flush=True)
