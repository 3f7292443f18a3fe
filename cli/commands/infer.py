"""`denoiser infer`: run a model over a dataset folder's sequences, one EXR per output frame (as infer jobs do)."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

from cli.commands.evaluate import add_run_options
from cli.main import UsageError
from cli.model_refs import runnable_method
from cli.options import add_model_options, params_from_args
from core.jobs.specs import InferParams


def add_commands(commands) -> None:
    parser = commands.add_parser(
        "infer", help="run a model over a dataset's sequences, history carried; one EXR per output frame",
        description="Step the model through every frame of the selected sequences (a split, named sequences, or "
                    "all), its history carried from frame to frame and reset at each sequence's start and at "
                    "camera cuts, and write OUT/SEQUENCE/frame_NNNN.exr: float32 R,G,B at the model's output "
                    "resolution. The same run as an infer job's.")
    parser.add_argument("--data", type=Path, required=True, metavar="DIR", help="dataset folder")
    # The infer job's parameters (core.jobs.specs.InferParams) but the dataset id, which is --data here.
    add_model_options(parser, InferParams, exclude=("dataset",), exclusive=[("split", "sequences")],
                      overrides={"model": {"metavar": "MODEL", "help": "a checkpoint file, a models:/ reference, a "
                                           "pretrained model or a registry method NAME[:PRESET]"},
                                 "sequences": {"metavar": "NAME"}})
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the output frames")
    add_run_options(parser)
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    parser.set_defaults(run=_run_infer)


def job_params(args) -> InferParams:
    return params_from_args(InferParams, args)


def _run_infer(args) -> int:
    from core.errors import DomainError
    from core.jobs.infer import select_sequences
    from model.deployment.infer import infer_sequences
    from model.io.dataset import Dataset
    from model.methods.registry import build_method
    from model.training.checkpoint import load_method

    params = job_params(args)
    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; give a folder")
    try:
        sequences = select_sequences(Dataset(args.data), params, str(args.data))
    except DomainError as error:
        raise UsageError(error.message) from None
    runnable, _ = runnable_method(params.model, "--model")
    if Path(runnable).is_file():
        method = load_method(runnable, scale=params.scale)
    else:
        method = build_method(runnable, params.scale or 1)
    method = method.for_inference().eval().to(args.device)
    ends = set(itertools.accumulate(len(s) for s in sequences))

    def say(done: int, total: int, message: str) -> None:
        if not args.quiet and done in ends:
            print(message, file=sys.stderr, flush=True)

    run = infer_sequences(method, sequences, args.out, args.device, on_frame=say)
    ms = "" if run["ms_per_frame"] is None else f", {run['ms_per_frame']:.1f} ms a frame (median)"
    print(f"{method.label} (x{method.scale}): wrote {run['frames']} frames of {len(sequences)} sequences to "
          f"{args.out}{ms}")
    return 0
