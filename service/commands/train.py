"""`denoiser train`: train a learned method on a dataset, in this process or in DDP ranks, tracked in MLflow."""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from service.cli import EXIT_FAILURE, HelpFormatter, UsageError, positive_int, registered_name

# As model.train.SCHEDULES and model.dataset.SPLITS; repeated so --help stays import-light.
SCHEDULES = ("cosine", "step", "constant")
SPLITS = ("train", "validation", "test")



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
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset folder")
    parser.add_argument("--method", required=True, metavar="NAME[:PRESET]",
                        help="learned method from the registry (see 'denoiser methods')")
    parser.add_argument("--scale", type=int, choices=(1, 2), default=1,
                        help="output / render resolution; the data needs references at this scale")
    length = parser.add_mutually_exclusive_group()
    length.add_argument("--steps", type=positive_int, default=1000, help="optimizer steps")
    length.add_argument("--epochs", type=positive_int, default=None,
                        help="passes over the training windows, instead of --steps")
    parser.add_argument("--crop", type=positive_int, default=64, metavar="N",
                        help="crop size in render pixels (the reference crop is SCALE times larger)")
    parser.add_argument("--frames-per-sample", type=positive_int, default=4, metavar="T",
                        help="consecutive frames unrolled per sample")
    parser.add_argument("--batch", type=positive_int, default=4, help="global batch size, split over the ranks")
    parser.add_argument("--lr", type=_positive_float, default=1e-3, help="Adam learning rate")
    parser.add_argument("--schedule", choices=SCHEDULES, default="cosine", help="learning-rate schedule")
    parser.add_argument("--warmup", type=_non_negative_int, default=50, metavar="STEPS",
                        help="steps of linear learning-rate warm-up")
    parser.add_argument("--spatial-weight", type=_non_negative_float, default=None,
                        help="weight of the spatial (SMAPE) loss; default: the method's own (1 for most)")
    parser.add_argument("--temporal-weight", type=_non_negative_float, default=None,
                        help="weight of the temporal loss; default: the method's own (0.25 for most)")
    parser.add_argument("--train-split", choices=SPLITS, default="train", help="split to train on")
    parser.add_argument("--validation-split", choices=SPLITS, default="validation",
                        help="split to validate on (may be empty: then no validation)")
    parser.add_argument("--validate-every", type=_non_negative_int, default=500, metavar="STEPS",
                        help="validate every N steps (0: only at the end)")
    parser.add_argument("--checkpoint-every", type=_non_negative_int, default=500, metavar="STEPS",
                        help="write OUT/last.pt every N steps (0: only at the end)")
    parser.add_argument("--out", type=Path, default=None, metavar="DIR",
                        help="output folder for checkpoints; none given: runs/METHOD[-PRESET]")
    parser.add_argument("--resume", action=argparse.BooleanOptionalAction, default=True,
                        help="continue from OUT/last.pt when it exists")
    parser.add_argument("--init-from", default=None, metavar="CHECKPOINT|PRETRAINED",
                        help="start a fresh run from this checkpoint's weights, or a pretrained model's (denoiser "
                             "pretrained: fine-tuning); same method and scale (a float32 JNDS checkpoint initializes "
                             "its -int8 preset for quantization-aware fine-tuning)")
    parser.add_argument("--world-size", type=positive_int, default=1, metavar="N", help="DDP ranks")
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                        help="auto: CUDA when available (NCCL between ranks), else CPU (gloo)")
    parser.add_argument("--threads", type=positive_int, default=None, metavar="N",
                        help="torch threads per rank; none given: torch's own, or the cores shared out among CPU ranks")
    parser.add_argument("--seed", type=int, default=0, help="seed of the weights, crops and augmentation")
    parser.add_argument("--tracking-uri", default=None, metavar="URI",
                        help="MLflow tracking URI; none given: $DENOISER_TRACKING_URI, "
                             "else sqlite:///./mlruns/mlflow.db")
    parser.add_argument("--experiment", default="denoiser", help="MLflow experiment name")
    parser.add_argument("--register-as", type=registered_name, default=None, metavar="NAME",
                        help="registered model name; none given: METHOD-PRESET-xSCALE")
    parser.add_argument("--no-tracking", action="store_true", help="do not log to MLflow")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(run=_run_train)


def _positive_float(text: str) -> float:
    value = _float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def _non_negative_float(text: str) -> float:
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _non_negative_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value}")
    return value


def _default_out(method: str) -> Path:
    return Path("runs") / re.sub(r"[^A-Za-z0-9._-]+", "-", method)


def _run_train(args) -> int:
    from model.train import LAST_CHECKPOINT, TrainConfig, prepare, resolve_device, resumable_checkpoint
    from workers.ddp import RankError

    config = TrainConfig(
        method=args.method, data=str(args.data), scale=args.scale, crop_size=args.crop,
        frames_per_sample=args.frames_per_sample, batch_size=args.batch,
        steps=None if args.epochs else args.steps, epochs=args.epochs, lr=args.lr,
        schedule=args.schedule, warmup_steps=args.warmup, spatial_weight=args.spatial_weight,
        temporal_weight=args.temporal_weight,
        train_split=args.train_split, validation_split=args.validation_split,
        validate_every=args.validate_every, checkpoint_every=args.checkpoint_every,
        out=str(args.out or _default_out(args.method)), resume=args.resume, world_size=args.world_size,
        device=args.device, num_threads=args.threads, seed=args.seed, tracking_uri=args.tracking_uri,
        experiment=args.experiment, register_as=args.register_as,
        init_from=_initial_weights(args.init_from))
    # Every input problem surfaces here, before any rank starts: ValueError / KeyError exit with status 2.
    resolve_device(config.device)
    crops, _, method = prepare(config)
    checkpoint = resumable_checkpoint(config, method, config.total_steps(len(crops)))
    if checkpoint is not None:
        print(f"resuming from {Path(config.out) / LAST_CHECKPOINT} at step {checkpoint['step']}", file=sys.stderr)

    progress = _ProgressBar(disabled=args.quiet)
    try:
        result = _train(config, track=not args.no_tracking, progress=progress)
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
    from model.train import train

    tracker = None
    if track:
        from workers.tracking import MLflowTracker

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
    """--init-from: a checkpoint file, or a pretrained model's name (its verified weights file)."""
    from model.pretrained import PretrainedError, get_pretrained, is_pretrained, verify

    if text is None or Path(text).is_file() or not is_pretrained(text):
        return text
    try:
        return str(verify(get_pretrained(text)))
    except PretrainedError as error:
        raise UsageError(str(error)) from None
