"""`denoiser train`: train a learned method on a dataset, in this process or in DDP ranks, tracked in MLflow."""

from __future__ import annotations

import re
import sys
from pathlib import Path

from cli.main import EXIT_FAILURE, HelpFormatter, registered_name
from cli.model_refs import model_checkpoint
from cli.options import add_model_options, params_from_args, settings_from_args
from core.jobs.specs import TrainParams
from model.training.training_settings import TrainConfig, TrainingSettings


def add_commands(commands) -> None:
    parser = commands.add_parser(
        "train", help="train a learned method on a dataset (checkpoints, exact resume, MLflow, DDP)",
        description="Train METHOD on random crops of FRAMES-PER-SAMPLE consecutive frames of the dataset's train "
                    "split, unrolled through the method with its history carried, with flips and brightness "
                    "augmentation; loss: SMAPE + L1 on the frame-to-frame change (log-tonemapped). Validates on "
                    "whole sequences of the validation split (PSNR, SMAPE, temporal error), writes OUT/last.pt "
                    "and OUT/best.pt, resumes exactly from OUT/last.pt, logs to MLflow and registers the final "
                    "model. With --world-size N > 1, N DistributedDataParallel ranks share the global batch.",
        formatter_class=HelpFormatter)
    # Every training option is a field of model.training.training_settings.TrainConfig: name, default, help and checks.
    add_model_options(parser, TrainConfig, exclusive=[("steps", "epochs")], aliases={"warmup_steps": ("--warmup",)},
                      overrides={"method": {"metavar": "NAME[:PRESET]"}, "data": {"metavar": "DIR"},
                                 "out": {"metavar": "DIR", "help": "output folder of the checkpoints (default: "
                                                                   "runs/METHOD[-PRESET] in the data folder, "
                                                                   "DENOISER_DATA_DIR)"},
                                 "register_as": {"type": registered_name, "metavar": "NAME"},
                                 "init_from": {"metavar": "CHECKPOINT|PRETRAINED|models:/REF"},
                                 "tracking_uri": {"metavar": "URI"}})
    # The train job's one field beyond the settings (its dataset is --data here; its nodes are workers of a queue,
    # while a local training runs on this machine).
    add_model_options(parser, TrainParams, exclude=("dataset", "nodes", *TrainingSettings.model_fields),
                      aliases={"track": ("--no-tracking",)})
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(run=_run_train)


def job_params(args) -> TrainParams:
    return params_from_args(TrainParams, args)


def _default_out(method: str) -> Path:
    """runs/METHOD[-PRESET] in the data folder, not the current one: a rerun from anywhere resumes."""
    from core.storage import get_storage

    return get_storage().runs / re.sub(r"[^A-Za-z0-9._-]+", "-", method)


def _run_train(args) -> int:
    from model.training.train import LAST_CHECKPOINT, prepare, resolve_device, resumable_checkpoint
    from workers.ddp import RankError

    config = settings_from_args(TrainConfig, args, out=getattr(args, "out", None) or str(_default_out(args.method)))
    if config.init_from:
        config.init_from = _initial_weights(config.init_from)
    # Every input problem surfaces here, before any rank starts: ValueError / KeyError exit with status 2.
    resolve_device(config.device)
    crops, _, method = prepare(config)
    note = crops.unused_note()
    if note:
        print(f"denoiser train: note: {note}", file=sys.stderr)
    checkpoint = resumable_checkpoint(config, method, config.total_steps(len(crops)))
    if checkpoint is not None:
        print(f"resuming from {Path(config.out) / LAST_CHECKPOINT} at step {checkpoint['step']}", file=sys.stderr)

    progress = _ProgressBar(disabled=args.quiet)
    try:
        result = _train(config, track=job_params(args).track, progress=progress)
    except RankError as error:
        progress.close()
        print(f"denoiser train: error: {error}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        progress.close()
    _print_result(result)
    return 0


def _train(config, track: bool, progress) -> dict:
    if config.world_size > 1:
        from workers.ddp import launch

        return launch(config, track=track, progress=progress)
    from model.training.train import train

    tracker = None
    if track:
        from core.tracking import MLflowTracker

        tracker = MLflowTracker(config.tracking_uri, config.experiment)
    return train(config, tracker=tracker, progress=progress)


class _ProgressBar:
    """A tqdm bar opened at the first report (its total and, after a resume, its start are known only then)."""

    def __init__(self, disabled: bool) -> None:
        self.disabled = disabled
        self.bar = None

    def __call__(self, current: int, total: int, message: str) -> None:
        if self.bar is None:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=current - 1, unit="step", disable=self.disabled, dynamic_ncols=True)
        self.bar.update(current - self.bar.n)
        # The message starts with "step N/M", which the bar shows already.
        self.bar.set_postfix_str(message.split(", ", 1)[-1], refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _print_result(result: dict) -> None:
    lines = [f"trained {result['steps']} steps ({result['epochs']:.2f} epochs) in {result['seconds']:.1f} s, "
             f"final loss {result['losses'].get('loss', float('nan')):.4f}"]
    validation = result.get("validation")
    if validation:
        lines.append("validation: " + ", ".join(f"{name} {value:.4g}" for name, value in validation.items()))
    lines.append(f"checkpoint: {result['checkpoint']}")
    if result.get("best_checkpoint"):
        lines.append(f"best checkpoint: {result['best_checkpoint']} (step {result['best_metric']['step']})")
    if result.get("run_id"):
        lines.append(f"MLflow run: {result['run_id']}")
    registered = result.get("registered_model")
    if registered:
        lines.append(f"registered model: {registered['name']} version {registered['version']} ({registered['uri']})")
    print("\n".join(lines))


def _initial_weights(text: str | None) -> str | None:
    """--init-from: a checkpoint file, a pretrained model's name or a registered model (their weights file)."""
    if text is None or Path(text).is_file():
        return text
    path = model_checkpoint(text, "--init-from")
    return text if path is None else str(path)
