"""`denoiser generate`, `import`, `scenes`, `summary` and `preview`: making and looking at datasets."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from cli.main import UsageError, size_list
from cli.options import add_model_options, params_from_args
from core.jobs.specs import GenerateParams
from core.names import SPLITS


def add_commands(commands) -> None:
    _add_generate(commands)
    _add_import(commands)
    _add_scenes(commands)
    _add_summary(commands)
    _add_preview(commands)


# ------------------------------------------------------------------------------------------- generate

def _add_generate(commands) -> None:
    from model.data.scenes import SCENES

    parser = commands.add_parser(
        "generate", help="render path-traced sequences with Mitsuba 3 into a dataset",
        description="Render one sequence per scene recipe into the dataset folder OUT (created if missing). "
                    "Each frame holds a 1spp noisy color (also split into diffuse and specular), noise-free "
                    "albedo, specular albedo, normal, depth and roughness, exact motion vectors, the camera "
                    "jitter, and box-filtered references (radiance, diffuse and specular albedo) at the requested "
                    "scales. Deterministic for a seed.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    # The generate job's parameters (core.jobs.specs.GenerateParams) but the dataset id, which is --out here.
    add_model_options(parser, GenerateParams, exclude=("dataset",), aliases={"scenes": ("--scene",)},
                      overrides={"scenes": {"metavar": "NAME", "help": "scene recipes; repeat for several, or "
                                            f"'all'. One of: {', '.join(sorted(SCENES))}"},
                                 "size": {"type": size_list, "metavar": "N|WxH", "shown_default": "128x128",
                                          "help": "render resolution (references are this times each scale)"},
                                 "scales": {"metavar": "S[,S]", "help": "reference scales to store (1, 2, 4); "
                                            "scale 1 is the 2x2 mean of scale 2"}})
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="dataset folder")
    parser.add_argument("--name", default=None,
                        help="sequence name (one scene only); default SCENE_sSEED")
    parser.add_argument("--variant", choices=("llvm_ad_rgb", "cuda_ad_rgb", "scalar_rgb"), default=None,
                        help="Mitsuba variant; default: cuda_ad_rgb on a GPU, else llvm_ad_rgb, else (no LLVM 19) "
                             "scalar_rgb")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(run=_run_generate)


def job_params(args) -> GenerateParams:
    return params_from_args(GenerateParams, args)


def _run_generate(args) -> int:
    from model.data.generate import generate_sequence
    from model.data.render import RenderSettings
    from model.data.scenes import SCENES

    params = job_params(args)
    scenes = sorted(SCENES) if "all" in params.scenes else list(dict.fromkeys(params.scenes))
    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        raise UsageError(f"unknown scene {', '.join(map(repr, unknown))}; known scenes: {', '.join(sorted(SCENES))}")
    if args.name and len(scenes) > 1:
        raise UsageError("--name applies to one scene only; drop it to name sequences SCENE_sSEED")
    from model.data.generate import default_sequence_name

    for scene in scenes:
        target = args.out / (args.name or default_sequence_name(scene, params.seed))
        if target.exists() and not params.overwrite:
            raise UsageError(f"sequence {target} already exists; pass --overwrite to replace it")
    from model.data.mitsuba_backend import choose_variant

    choose_variant(args.variant)  # a variant this machine cannot run: exit 2 before the dataset folder is made
    width, height = params.size
    settings = RenderSettings(width=width, height=height, ref_spp=params.ref_spp, ref_scales=tuple(params.scales),
                              albedo_spp=params.albedo_spp, max_depth=params.max_depth, variant=args.variant,
                              jitter=params.jitter)
    for scene in scenes:
        generate_sequence(scene, args.out, frames=params.frames, settings=settings, seed=params.seed,
                          split=params.split, name=args.name, half=params.half, overwrite=params.overwrite,
                          progress=not args.quiet)
    _print_summary(args.out)
    return 0


# --------------------------------------------------------------------------------------------- import

def _add_import(commands) -> None:
    parser = commands.add_parser(
        "import", help="convert a folder of another renderer's EXR frames into a sequence of a dataset",
        description="Read every .exr in SRC (name order) in the layout, convert it to the frame bundle (channels, "
                    "motion, depth and normal conventions, jitter), and write one validated sequence into the "
                    "dataset folder OUT (created if missing). References: same-named high-sample renders in "
                    "SRC/references or --references. Channels the layout does not use are ignored and listed; "
                    "normals off unit length by lossy compression are renormalised and listed; data that looks "
                    "wrong (motion that reprojects worse than none, normals that turn with the camera, depth that "
                    "shrinks towards the horizon) is reported as warnings.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("source", type=Path, metavar="SRC", help="folder of the renderer's frame EXRs")
    parser.add_argument("--layout", required=True, metavar="NAME|FILE",
                        help="built-in layout (denoiser, blender-cycles, generic) or a layout file (.toml, .json)")
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="dataset folder")
    parser.add_argument("--references", type=Path, default=None, metavar="DIR",
                        help="folder of high-sample renders named as the frames; default SRC/references if present")
    parser.add_argument("--name", default=None, help="sequence name; default the name of SRC")
    parser.add_argument("--scene", default=None, help="scene name recorded in the dataset (for held-out splits)")
    parser.add_argument("--split", choices=SPLITS, default="train",
                        help="split the sequence belongs to")
    parser.add_argument("--fov-y", type=_degrees, default=None, metavar="DEGREES",
                        help="vertical field of view, for layouts with planar depth (overrides the layout and the "
                             "header)")
    parser.add_argument("--half", action="store_true", help="store EXR channels as half floats")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing sequence of the same name")
    parser.set_defaults(run=_run_import)


def _degrees(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of degrees") from None
    if not 0 < value < 180:
        raise argparse.ArgumentTypeError(f"{text} is not between 0 and 180 degrees")
    return value


def _run_import(args) -> int:
    import sys

    from model.io.importer import import_sequence
    from model.layouts import LayoutError, load_layout

    try:
        layout = load_layout(args.layout)
    except LayoutError as error:
        raise UsageError(str(error)) from None
    report = import_sequence(args.source, layout, args.out, name=args.name, references=args.references,
                             scene=args.scene, split=args.split, fov_y_degrees=args.fov_y, half=args.half,
                             overwrite=args.overwrite)
    scales = ",".join(str(scale) for scale in report.scales) or "none"
    print(f"imported {report.frames} frames from {args.source} ({layout.name}) into {report.sequence} "
          f"(references at scales: {scales})")
    if report.ignored_channels:
        print(f"ignored channels: {', '.join(report.ignored_channels)}")
    if report.ignored_files:  # a renderer's own manifest.json, previews: not frames, not read
        print(f"ignored {len(report.ignored_files)} file(s) that are not frames: {', '.join(report.ignored_files)}")
    for repair in report.repairs:
        print(f"repaired {repair}")
    for warning in report.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    return 0


# ----------------------------------------------------------------------------------- scenes, summary

def _add_scenes(commands) -> None:
    parser = commands.add_parser("scenes", help="list the scene recipes of the generator")
    parser.set_defaults(run=_run_scenes)


def _run_scenes(args) -> int:
    from model.data.scenes import DESCRIPTIONS

    width = max(len(name) for name in DESCRIPTIONS)
    for name in sorted(DESCRIPTIONS):
        print(f"{name:<{width}}  {DESCRIPTIONS[name]}")
    return 0


def _add_summary(commands) -> None:
    parser = commands.add_parser("summary", help="print a dataset's sequences, splits, resolutions and scales")
    parser.add_argument("dataset", type=Path, help="dataset folder")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.set_defaults(run=_run_summary)


def _run_summary(args) -> int:
    _print_summary(args.dataset, as_json=args.json)
    return 0


def _print_summary(root: Path, as_json: bool = False) -> None:
    from model.io.dataset import Dataset

    dataset = Dataset(root)
    print(json.dumps(dataset.summary(), indent=2) if as_json else dataset.format_summary())


# ------------------------------------------------------------------------------------------- preview

def _add_preview(commands) -> None:
    parser = commands.add_parser(
        "preview", help="save a PNG of one frame's buffers side by side, or of one output EXR",
        description="FRAME is a frame bundle EXR (a contact sheet of its buffers), a sequence folder, an output EXR "
                    "(the plain R/G/B images the service, denoiser stream and denoiser infer write: the image "
                    "itself, display-encoded as clip(x, 0, 1) ** (1/2.2), at its own size) or a folder of them.")
    parser.add_argument("frame", type=Path,
                        help="frame or output EXR file, or a sequence or output folder (then --index picks)")
    parser.add_argument("--index", type=int, default=0, help="frame index within a folder (default 0; -1: the last)")
    parser.add_argument("--out", type=Path, required=True, help="PNG file to write")
    parser.set_defaults(run=_run_preview)


def _run_preview(args) -> int:
    from model.io.exr import is_image_exr, read_frame
    from model.io.preview import save_buffer_sheet

    if args.frame.is_dir() and (args.frame / "manifest.json").is_file():
        from model.io.dataset import Sequence

        sequence = Sequence(args.frame)
        index = _folder_index(args, len(sequence))
        out = save_buffer_sheet(sequence[index], args.out, f"{sequence.name}, frame {index}")
        print(f"wrote {out}")
        return 0
    path = args.frame
    if path.is_dir():  # an output folder (OUT/frame_NNNN.exr): no manifest, the files in name order
        files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() == ".exr")
        if not files:
            raise UsageError(f"{path}: neither a sequence folder (manifest.json) nor a folder of EXR files")
        path = files[_folder_index(args, len(files))]
    if is_image_exr(path):
        # The same reader and PNG writer as `denoiser stream --png`: one display encoding of output images.
        from client.frames import decode_image_exr, encode_png

        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_bytes(encode_png(decode_image_exr(path.read_bytes(), source=str(path))))
        print(f"wrote {args.out} (output image {path.name}, display-encoded)")
        return 0
    frame = read_frame(path)
    title = f"{path.name}"
    out = save_buffer_sheet(frame, args.out, title)
    print(f"wrote {out}")
    return 0


def _folder_index(args, count: int) -> int:
    index = count + args.index if args.index < 0 else args.index
    if not 0 <= index < count:
        raise UsageError(f"{args.frame}: --index {args.index} is out of range (0..{count - 1}, or -1 for the last)")
    return index
