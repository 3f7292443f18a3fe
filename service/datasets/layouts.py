"""Uploads in other layouts: what an unpacked archive needs before ``service.datasets.ingest`` validates it.

- Frame bundles with channels the format does not use (an extra AOV, an alpha, an extra part) are stored without
  them: such a file is read in the ``denoiser`` layout (strict about values) and written again in place.
- Archives in another renderer's layout (``?layout=blender-cycles``) hold one folder per sequence with the
  frame EXRs and optionally ``references/``; each is converted with ``model.io.importer`` (as ``denoiser import``)
  into a dataset folder in the upload's workspace, which is then validated like any upload.

Errors are the library's (FrameError, DatasetError); ``service.datasets.ingest`` turns them into upload errors.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import OpenEXR

from model.io.dataset import DATASET_FORMAT, MANIFEST, SEQUENCE_FORMAT, DatasetError
from model.io.exr import CHANNEL_SLOTS, REFERENCE_PART_PATTERN, write_frame
from model.io.importer import import_sequence
from model.layouts import BUILTIN_LAYOUTS, Layout, read_layout_frame


@dataclass
class UploadNotes:
    """What an upload's conversion ignored or found suspicious (for the response headers)."""

    ignored_channels: set[str] = field(default_factory=set)
    warnings: list[str] = field(default_factory=list)
    ignored_files: list[str] = field(default_factory=list)  # upload paths that are not frames, left out


def _has_only_frame_channels(path: Path) -> bool:
    """True when every part and channel of the file is one the frame bundle format uses (header read only)."""
    try:
        parts = OpenEXR.File(str(path), header_only=True).parts
    except Exception:  # unreadable: the validation that follows names the problem
        return True
    for index, part in enumerate(parts):
        if index and not REFERENCE_PART_PATTERN.fullmatch(part.name() or ""):
            return False
        if any(channel.name not in CHANNEL_SLOTS for channel in part.header.get("channels", ())):
            return False
    return True


def strip_unused_channels(root: Path, notes: UploadNotes) -> None:
    """Rewrite every frame EXR under ``root`` that holds channels or parts the format does not use, without them."""
    denoiser = BUILTIN_LAYOUTS["denoiser"]
    for path in sorted(root.rglob("*.exr")):
        if not path.is_file() or _has_only_frame_channels(path):
            continue
        read = read_layout_frame(path, denoiser, mode="strict")
        notes.ignored_channels.update(read.ignored_channels)
        write_frame(path, read.frame)


def _manifest_format(path: Path):
    try:
        return json.loads(path.read_text()).get("format")
    except (OSError, ValueError, AttributeError):
        return None


def _holds_frames(folder: Path) -> bool:
    return any(path.suffix.lower() == ".exr" for path in folder.iterdir() if path.is_file())


def import_renderer_folders(root: Path, top: Path, destination: Path, layout: Layout, split: str,
                            notes: UploadNotes) -> Path:
    """Convert the renderer sequence folders of the upload unpacked at ``root`` into a dataset folder at
    ``destination``; return it.

    ``top`` (``root`` or a single folder it wraps) is one sequence folder (its frames directly inside) or a folder
    of them; a sequence is named after its folder. A manifest.json is this project's only when its ``format`` says
    so; a renderer's or a pipeline's own, like any file that is not a frame EXR, is left out and named in ``notes``."""
    ours = [folder for folder in [top, *sorted(p for p in top.iterdir() if p.is_dir())]
            if _manifest_format(folder / MANIFEST) in (SEQUENCE_FORMAT, DATASET_FORMAT)]
    if ours:
        raise DatasetError(f"the upload holds {ours[0].relative_to(root) / MANIFEST} (the frame bundle format); "
                           f"upload it without layout= (or layout=denoiser)")
    if _holds_frames(top):
        if top == root:
            raise DatasetError("the archive holds frame EXRs at its top level; put each sequence's frames in a "
                               "folder named after the sequence")
        folders = [top]
    else:
        folders = sorted(entry for entry in top.iterdir() if entry.is_dir() and _holds_frames(entry))
        if not folders:
            raise DatasetError(f"no folder of frame EXRs in the upload (layout '{layout.name}' expects one folder per "
                               f"sequence holding its frames, and optionally references/)")
    for folder in folders:
        report = import_sequence(folder, layout, destination, split=split)
        notes.ignored_files.extend(str((folder / name).relative_to(root)) for name in report.ignored_files)
        notes.ignored_channels.update(report.ignored_channels)
        notes.warnings.extend(f"{folder.name}: {warning}" for warning in report.warnings)
    return destination
