"""`denoiser export`: a trained model's per-frame step as an ONNX file for engines (model/deployment/export.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from cli.main import UsageError, size_option
from cli.model_refs import model_checkpoint


def add_commands(commands) -> None:
    parser = commands.add_parser(
        "export", help="export a trained model's per-frame step (history as explicit inputs/outputs) to ONNX",
        description="Write MODEL's per-frame step as an ONNX graph: the frame's buffers (NCHW, N = 1) and the "
                    "history tensors state.NAME in, the output and state_out.NAME out (feed them back; zeros on the "
                    "first frame and after a cut). The fused family exports its network with OIDN's output as the "
                    "input spatial_estimate (the engine runs OIDN). The file is then run with onnxruntime over a "
                    "short random sequence against PyTorch and the worst difference printed (tolerance: 1e-4 "
                    "absolute + 1e-4 relative). OIDN-only methods, filters without weights and int8 JNDS are "
                    "refused, saying why. Each stage is named on stderr as it starts, and the seconds of every "
                    "stage are printed at the end (docs/export.md, \"Export time\").")
    parser.add_argument("model", metavar="MODEL",
                        help="a checkpoint file, a pretrained model's name (denoiser pretrained), or a registered "
                             "model (models:/NAME@ALIAS, models:/NAME/VERSION) in the service's registry")
    parser.add_argument("--format", choices=("onnx",), default="onnx",
                        help="onnx, the one format (TorchScript cannot save the methods' kernel ops: docs/export.md)")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE", help="the file to write, e.g. model.onnx")
    parser.add_argument("--size", type=size_option, default=(128, 128), metavar="N|WxH",
                        help="render resolution the graph is exported for (default 128x128)")
    parser.add_argument("--with-optional-buffers", action="store_true",
                        help="also take diffuse, specular, specular_albedo and roughness as inputs")
    parser.add_argument("--no-check", action="store_true", help="skip the onnxruntime check against PyTorch")
    parser.set_defaults(run=_run_export)


def load_model(text: str):
    """The trained method MODEL names (checkpoint file, pretrained name, models:/ reference, or a registry name to
    say why it cannot be exported)."""
    from model.training.checkpoint import load_method

    if Path(text).is_file():
        return load_method(text)
    path = model_checkpoint(text, "MODEL")
    if path is not None:
        return load_method(path)
    from model.methods.registry import build_method

    try:
        method = build_method(text)
    except (KeyError, ValueError):
        raise UsageError(f"MODEL {text!r} is no checkpoint file, pretrained model, models:/ reference or method")
    if method.learned:
        raise UsageError(f"{method.label} by name has untrained weights; export a trained checkpoint, a pretrained "
                         f"model or a registered one")
    return method


def _run_export(args) -> int:
    from model.deployment.export import ExportError, TOLERANCE, Stages, check_export, export_step

    if args.out.is_dir():
        raise UsageError(f"--out {args.out} is a folder; give a file name such as model.onnx")
    stages = Stages(lambda line: print(f"export: {line}", file=sys.stderr, flush=True))
    with stages.stage("load", args.model):
        method = load_model(args.model)
    width, height = args.size
    try:
        info = export_step(method, args.out, args.format, height=height, width=width,
                           with_optional=args.with_optional_buffers, stages=stages)
    except ExportError as error:
        raise UsageError(str(error)) from None
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes): {method.label} at scale {method.scale}, "
          f"{width}x{height} in")
    print(json.dumps({key: info[key] for key in ("inputs", "state", "outputs", "first_frame", "spatial_estimate",
                                                 "sample_mean")}, indent=2))
    if not args.no_check:
        worst = check_export(method, args.out, info, stages=stages)
    print(f"export: seconds per stage: {stages.summary()}", file=sys.stderr, flush=True)
    if not args.no_check:
        verdict = "within" if worst <= 1 else "OUTSIDE"
        print(f"onnxruntime against PyTorch over 4 frames (history carried): worst difference {worst:.3g} of the "
              f"tolerance ({TOLERANCE['atol']:g} absolute + {TOLERANCE['rtol']:g} relative): {verdict}")
        if worst > 1:
            return 1
    return 0
