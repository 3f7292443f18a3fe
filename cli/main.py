"""The `denoiser` command line.

Each subcommand imports what it needs when it runs, so `denoiser --help` stays fast. Errors the user can fix
(bad options, bad files) print one line naming the problem and exit with status 2; other failures exit 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# Each module adds its subcommands with add_commands(subparsers); commands import their heavy
# dependencies only when they run.
COMMAND_MODULES = ("cli.commands.data", "cli.commands.evaluate", "cli.commands.train",
                   "cli.commands.client", "cli.commands.serve", "cli.commands.stability",
                   "cli.commands.benchmark", "cli.commands.fit", "cli.commands.pretrained",
                   "cli.commands.export", "cli.commands.infer")

EXIT_USAGE = 2
EXIT_FAILURE = 1


class UsageError(Exception):
    """A problem with the user's input: reported as one line, exit status 2."""


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def registered_name(text: str) -> str:
    """A name to register a model as: anything MLflow takes but 'auto', which sessions read as "choose for me"."""
    from core.names import AUTO_MODEL, AUTO_MODEL_RESERVED

    if text == AUTO_MODEL:
        raise argparse.ArgumentTypeError(AUTO_MODEL_RESERVED)
    return text


def device_option(text: str) -> str:
    """A torch device the methods can run on here: cpu, cuda or cuda:N (checked when the options are parsed, so a
    typo or a missing GPU exits 2 before any data is read)."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}") from None
    if device.type not in ("cpu", "cuda"):
        raise argparse.ArgumentTypeError(f"expected cpu, cuda or cuda:N, got {text!r}")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise argparse.ArgumentTypeError(f"{text}: no CUDA device is available")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise argparse.ArgumentTypeError(f"{text}: only {torch.cuda.device_count()} CUDA device(s) here")
    return text


def size_option(text: str) -> tuple[int, int]:
    """'128' -> (128, 128); '160x96' -> (160, 96) as width x height."""
    parts = text.lower().split("x")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must be N or WIDTHxHEIGHT, got {text!r}") from None
    if len(values) == 1:
        values *= 2
    if len(values) != 2 or min(values) < 1:
        raise argparse.ArgumentTypeError(f"size must be N or WIDTHxHEIGHT with positive numbers, got {text!r}")
    return values[0], values[1]


def size_list(text: str) -> list[int]:
    """``size_option`` as [width, height]: the command-line form of job parameters' size fields."""
    return list(size_option(text))


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows defaults, except for options without one (None) and flags (False), where "(default: ...)" is noise."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.required or action.default is None or action.default is False:
            return action.help
        return super()._get_help_string(action)


# ---------------------------------------------------------------------------------------------- main

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="denoiser", description="Real-time neural denoisers for path-traced "
                                     "frames: data generation, training, evaluation and serving.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMAND_MODULES:
        importlib.import_module(module).add_commands(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    from model.io.frames import FrameError
    from model.deployment.malloc import tune_for_large_frames

    args = build_parser().parse_args(argv)
    tune_for_large_frames()  # before any frame is read: a 1080p step otherwise faults its tensors in every time
    try:
        from core.settings import get_settings

        get_settings()  # invalid settings are refused here; valid ones set the model library's switches
        return args.run(args)
    except (UsageError, FrameError, FileNotFoundError, FileExistsError, KeyError, ValueError) as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"denoiser {args.command}: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"denoiser {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
