"""Importing a renderer's frames: a folder of EXRs in some layout -> one validated sequence of a dataset.

A renderer's sequence folder holds one EXR per frame (``*.exr``, in name order; other files, a renderer's or a
pipeline's own manifest.json among them, are skipped and named in the report) and,
optionally, high-sample renders of the same frames under the same names in a ``references/`` subfolder (or
another folder given as ``references``). Each frame is read in the layout (``model.layouts``, mode "import":
lossy-compressed normals are renormalised), numbered by its position, given its reference (a render at an integer
multiple s of the resolution becomes the scale-s reference, and its 2x2 box mean the scale-1 one when s = 2), and
written with ``model.io.dataset.SequenceWriter`` (all or nothing). The layout's mismatch checks
(``model.layouts.checks``) run over the frames; their warnings, the ignored channels and the repairs are returned
and recorded in the sequence manifest's metadata.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from model.io.dataset import SPLITS, Dataset, DatasetError, SequenceWriter
from model.io.frames import FrameBundle, FrameValidationError, box_downsample
from model.layouts import Layout, read_layout_frame, read_layout_reference
from model.layouts.checks import SequenceChecks

REFERENCES_FOLDER = "references"


@dataclass
class ImportReport:
    sequence: Path
    frames: int = 0
    scales: tuple[int, ...] = ()
    ignored_channels: list[str] = field(default_factory=list)
    repairs: list[str] = field(default_factory=list)  # "frame_0003.exr: normal: 12 pixels renormalised ..."
    warnings: list[str] = field(default_factory=list)
    ignored_files: list[str] = field(default_factory=list)  # files of the folder that are not frames


def frame_files(folder: Path) -> list[Path]:
    """The EXR files of a renderer's sequence folder, in name order."""
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder} is not a folder")
    files = sorted(path for path in folder.iterdir() if path.is_file() and path.suffix.lower() == ".exr"
                   and not path.name.startswith("."))
    if not files:
        raise DatasetError(f"{folder} holds no .exr files")
    return files


def ignored_files(folder: Path, frames: list[Path]) -> list[str]:
    """The files directly in ``folder`` that are not among ``frames`` (a renderer's manifest.json, previews)."""
    chosen = set(frames)
    return sorted(path.name for path in folder.iterdir() if path.is_file() and path not in chosen)


def reference_files(frames: list[Path], references: Path | None) -> list[Path] | None:
    """The reference file of every frame (same name in ``references``), or None without references."""
    if references is None:
        default = frames[0].parent / REFERENCES_FOLDER
        if not default.is_dir():
            return None
        references = default
    if not references.is_dir():
        raise FileNotFoundError(f"references folder {references} is not a folder")
    paths = [references / frame.name for frame in frames]
    missing = [path.name for path in paths if not path.is_file()]
    if missing:
        raise DatasetError(f"{references} lacks the references of {len(missing)} frame(s), first {missing[0]}; every "
                           f"frame needs one, under the frame's file name")
    return paths


def with_reference(frame: FrameBundle, targets: dict[str, np.ndarray], source: str) -> FrameBundle:
    """``frame`` with a reference render's target buffers at the scale their size gives."""
    height, width = targets["reference"].shape[:2]
    scale = width // frame.width
    if scale < 1 or width != scale * frame.width or height != scale * frame.height:
        raise FrameValidationError(source, "reference", f"is {width}x{height}, not an integer multiple of the frame's "
                                                        f"{frame.width}x{frame.height}")
    by_name = {name: {scale: array} for name, array in targets.items()}
    if scale == 2:  # the frame bundle's scale-1 reference is the 2x2 mean of the scale-2 one
        for by_scale in by_name.values():
            by_scale[1] = box_downsample(by_scale[2], 2)
    return dataclasses.replace(
        frame, references=by_name["reference"], reference_albedos=by_name.get("reference_albedo", {}),
        reference_specular_albedos=by_name.get("reference_specular_albedo", {}))


def import_sequence(source: str | Path, layout: Layout, out: str | Path, *, name: str | None = None,
                    references: str | Path | None = None, scene: str | None = None, split: str = "train",
                    fov_y_degrees: float | None = None, half: bool = False,
                    overwrite: bool = False) -> ImportReport:
    """Import the renderer's sequence folder ``source`` into the dataset folder ``out`` (created if missing) as
    sequence ``name`` (default: the folder's name). Nothing is written unless every frame converts and validates.
    """
    source = Path(source)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose one of {', '.join(SPLITS)}")
    name = name or source.resolve().name
    files = frame_files(source)
    reference_paths = reference_files(files, None if references is None else Path(references))
    out = Path(out)
    dataset = Dataset.open_or_create(out)
    target = dataset.root / name
    if target.exists() and not overwrite:
        raise FileExistsError(f"sequence {target} already exists; pass overwrite to replace it")
    report = ImportReport(sequence=target, ignored_files=ignored_files(source, files))
    checks = SequenceChecks(hints=layout.name)
    ignored: set[str] = set()
    metadata = {"imported_from": str(source), "layout": layout.name,
                "references": None if reference_paths is None else str(reference_paths[0].parent)}
    writer = SequenceWriter(target, name, scene=scene, metadata=metadata, half=half, overwrite=overwrite)
    with writer:
        for position, path in enumerate(files):
            read = read_layout_frame(path, layout, mode="import", fov_y_degrees=fov_y_degrees)
            frame = dataclasses.replace(read.frame, frame_index=position, sequence=name)
            if reference_paths is not None:
                frame = with_reference(frame, read_layout_reference(reference_paths[position], layout),
                                       str(reference_paths[position]))
            ignored.update(read.ignored_channels)
            report.repairs.extend(f"{path.name}: {repair}" for repair in read.repairs)
            checks.add(frame)
            writer.add(frame)
            report.scales = frame.scales
        report.frames = len(files)
        report.ignored_channels = sorted(ignored)
        report.warnings = checks.warnings()
        writer.metadata.update(ignored_channels=report.ignored_channels, repairs=report.repairs,
                               warnings=report.warnings)
    dataset.add_sequence_dir(name, split, replace=overwrite)
    return report
