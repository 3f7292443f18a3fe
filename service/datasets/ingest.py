"""Archive uploads: unpacked sequences validated in staging, then moved into ``datasets/<id>`` all or nothing.

Every frame is read with ``model.io.exr.read_frame`` and checked against its sequence manifest by
``model.io.dataset.Sequence`` before anything is moved. A new dataset is assembled completely in staging
(manifest included) and renamed into place in one step; sequences added to an existing dataset are renamed in
one by one, then the dataset manifest is replaced atomically; a failure on the way renames every moved folder
back (and restores replaced ones).
"""

from __future__ import annotations

import errno
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from model.io.dataset import (
    DATASET_FORMAT,
    Dataset,
    DatasetError,
    MANIFEST,
    SEQUENCE_FORMAT,
    SPLITS,
    Sequence,
    json_problem,
    write_json_atomically,
)
from model.io.exr import DecodeTooLarge, FrameTooLarge, check_frame_file_pixels
from model.io.frames import BUFFERS, FrameBundle, FrameError
from model.io.importer import REFERENCES_FOLDER
from model.layouts import Layout
from service.datasets.archives import unpack_archive
from service.datasets.catalog import checked_sequence_name, dataset_exists, describe_dataset
from service.datasets.errors import FrameTooLargeUpload, InvalidUpload, UnknownDataset, UploadConflict
from service.datasets.layouts import UploadNotes, import_renderer_folders, strip_unused_channels
from service.datasets.descriptions import DatasetDetail
from core.dataset_lock import dataset_lock
from core.storage import Storage


@dataclass
class _Staged:
    """A validated sequence folder in staging, ready to be moved into a dataset."""

    name: str
    path: Path
    split: str
    scene: str | None


def find_sequences(root: Path, default_split: str, ignored: list[str] | None = None) -> list[_Staged]:
    """Validate an unpacked upload and return its sequences; InvalidUpload naming the path on any problem.

    Accepted layouts: sequence folders (each with manifest.json) at the top or under one wrapping folder,
    a whole dataset folder (manifest.json with splits, possibly wrapped), or one sequence folder's contents.
    Sequences without a split in the upload get ``default_split``. A manifest.json is this project's only when its
    ``format`` says so: another (a renderer's or a pipeline's own) and any file that is not an EXR and lies outside
    the sequences' frames is left out, its path appended to ``ignored``; an unlisted EXR or folder is still refused.
    """
    ignored = [] if ignored is None else ignored
    top = _unwrap(root)
    try:
        if not (top / MANIFEST).is_file():
            return _folder_sequences(top, root, default_split, ignored)
        manifest_format = _manifest_format(top / MANIFEST, root)
        if manifest_format == DATASET_FORMAT:
            return _dataset_sequences(top, root, ignored)
        if manifest_format == SEQUENCE_FORMAT:
            return [_validated_sequence(top, root, default_split, ignored, check_folder_name=False)]
        return _folder_sequences(top, root, default_split, ignored)  # a foreign manifest: one more file left out
    except (DatasetError, FrameError) as error:
        raise _invalid(error, root) from None


def _foreign(entry: Path) -> bool:
    """A file that is not a frame (nor this project's manifest, which the caller has read): left out of uploads."""
    return entry.is_file() and entry.suffix.lower() != ".exr"


def _unwrap(root: Path) -> Path:
    """Step into single wrapping folders ("export/seq_a/...") until a level holds a manifest or several entries."""
    top = root
    while not (top / MANIFEST).exists():
        entries = list(top.iterdir())
        if len(entries) != 1 or not entries[0].is_dir():
            break
        inner = entries[0] / MANIFEST
        if inner.is_file() and _manifest_format(inner, root) == SEQUENCE_FORMAT:
            break  # entries[0] is the one sequence folder of the upload
        top = entries[0]
    return top


def _manifest_format(path: Path, root: Path) -> Any:
    try:
        content = json.loads(path.read_text())
    except (ValueError, RecursionError) as error:
        relative = _relative(path, root)
        raise InvalidUpload("invalid_dataset", f"{relative}: {json_problem(error)}", {"path": relative}) from None
    return content.get("format") if isinstance(content, dict) else None


def _dataset_sequences(top: Path, root: Path, ignored: list[str]) -> list[_Staged]:
    dataset = Dataset(top)
    listed = {checked_sequence_name(name) for name in dataset.names()}
    for entry in sorted(top.iterdir()):
        if entry.name != MANIFEST and entry.name not in listed and _foreign(entry):
            ignored.append(_relative(entry, root))
        elif entry.name != MANIFEST and entry.name not in listed:
            relative = _relative(entry, root)
            raise InvalidUpload("invalid_dataset", f"{relative} is not listed in "
                                                   f"{_relative(top / MANIFEST, root)}", {"path": relative})
    if not listed:
        raise InvalidUpload("invalid_dataset", f"{_relative(top / MANIFEST, root)} lists no sequences",
                            {"path": _relative(top / MANIFEST, root)})
    return [_validated_sequence(top / name, root, dataset.split_of(name), ignored) for name in sorted(listed)]


def _folder_sequences(top: Path, root: Path, split: str, ignored: list[str]) -> list[_Staged]:
    ignored.extend(_relative(entry, root) for entry in sorted(top.iterdir()) if _foreign(entry))
    entries = sorted(entry for entry in top.iterdir() if not _foreign(entry))
    if not entries:
        raise InvalidUpload("invalid_dataset", "the upload holds no sequence folder (folders holding manifest.json "
                                               "and frame EXRs)", {"path": "."})
    for entry in entries:
        relative = _relative(entry, root)
        if not entry.is_dir():
            raise InvalidUpload("invalid_dataset", f"{relative} is not inside a sequence folder (expected "
                                                   f"folders holding manifest.json and frame EXRs)",
                                {"path": relative})
        if not (entry / MANIFEST).is_file():
            raise InvalidUpload("missing_manifest", f"sequence folder {relative} has no {MANIFEST}",
                                {"path": relative})
    return [_validated_sequence(entry, root, split, ignored) for entry in entries]


def _validated_sequence(folder: Path, root: Path, split: str, ignored: list[str],
                        check_folder_name: bool = True) -> _Staged:
    """Open the sequence, read every frame (validated and checked against the manifest), and check the folder
    holds nothing else. The folder name must be the sequence's name: frames carry it in their headers."""
    sequence = Sequence(folder)
    checked_sequence_name(sequence.name)
    relative = _relative(folder, root) or "."
    if check_folder_name and folder.name != sequence.name:
        raise InvalidUpload("invalid_dataset", f"sequence folder {relative} holds sequence {sequence.name!r} "
                                               f"(per its {MANIFEST}); the folder must be named after it",
                            {"path": relative})
    listed = {sequence.frame_path(index).name for index in range(len(sequence))} | {MANIFEST}
    for entry in sorted(folder.iterdir()):
        if entry.name not in listed and _foreign(entry):
            ignored.append(_relative(entry, root))
        elif entry.name not in listed:
            path = _relative(entry, root)
            raise InvalidUpload("invalid_dataset", f"{path} is not a frame listed in {relative}/{MANIFEST}",
                                {"path": path})
    first_buffers: list[str] | None = None
    for index in range(len(sequence)):
        try:
            buffers = frame_buffers(sequence[index])
        except DatasetError as error:  # the frame disagrees with the manifest: still the frame's problem
            path = _relative(sequence.frame_path(index), root)
            raise InvalidUpload("invalid_frame", _invalid(error, root).message, {"path": path}) from None
        if first_buffers is None:
            first_buffers = buffers
        elif buffers != first_buffers:
            path = _relative(sequence.frame_path(index), root)
            raise InvalidUpload("invalid_frame", f"{path}: buffers {', '.join(buffers)} differ from the first "
                                                 f"frame's {', '.join(first_buffers)}", {"path": path})
    return _Staged(sequence.name, folder, split, sequence.scene)


def frame_buffers(frame: FrameBundle) -> list[str]:
    """Names of the buffers a frame has, in BUFFERS order (targets counted when present at any scale)."""
    present = set(frame.render_buffers())
    present.update(name for scale in frame.scales for name in frame.target_buffers(scale))
    return [name for name in BUFFERS if name in present]


def _relative(path: Path, root: Path) -> str:
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.as_posix()


def _invalid(error: DatasetError | FrameError, root: Path) -> InvalidUpload:
    """The library's message with staging paths made relative to the upload, so it names archive paths."""
    message = str(error).replace(f"{root}/", "").replace(str(root), ".")
    if isinstance(error, FrameError):
        details = {"path": _relative(Path(error.source), root), "buffer": error.buffer, "problem": error.problem}
        return InvalidUpload("invalid_frame", message, details)
    return InvalidUpload("invalid_dataset", message)


def _create_dataset(storage: Storage, dataset_id: str, sequences: list[_Staged], work: Path) -> None:
    """Assemble a complete dataset in ``work`` and rename it to datasets/<id>; caller holds the lock."""
    target = storage.dataset(dataset_id)
    if target.exists():
        raise UploadConflict("dataset_exists", f"dataset {dataset_id!r} already exists; add sequences with "
                                               f"POST /datasets/{dataset_id}/sequences",
                             {"dataset": dataset_id})
    assembled = work / "dataset"
    dataset = Dataset.create(assembled)
    moved: list[_Staged] = []
    try:
        for sequence in sequences:
            os.rename(sequence.path, assembled / sequence.name)
            moved.append(sequence)
            dataset.add_sequence_dir(sequence.name, sequence.split)
        storage.datasets.mkdir(parents=True, exist_ok=True)
        os.rename(assembled, target)
    except BaseException as error:
        # Staged folders go back where they were (a staged frame upload survives for another try).
        if assembled.is_dir():
            for sequence in moved:
                os.rename(assembled / sequence.name, sequence.path)
        if isinstance(error, OSError) and error.errno in (errno.EEXIST, errno.ENOTEMPTY):
            # Another process without our lock (should not happen) created it in the meantime.
            raise UploadConflict("dataset_exists", f"dataset {dataset_id!r} already exists",
                                 {"dataset": dataset_id}) from None
        raise


def _add_to_dataset(storage: Storage, dataset_id: str, sequences: list[_Staged], work: Path,
                    replace: bool) -> None:
    """Move sequences into an existing dataset, all or none; caller holds the lock."""
    target = storage.dataset(dataset_id)
    existing = Dataset(target)
    taken = sorted(s.name for s in sequences if s.name in set(existing.names()))
    if taken and not replace:
        raise UploadConflict("sequence_exists", f"dataset {dataset_id!r} already has sequence(s) "
                                                f"{', '.join(taken)}; pass replace=true to replace them",
                             {"dataset": dataset_id, "sequences": taken})
    manifest = json.loads((target / MANIFEST).read_text())
    moved: list[tuple[_Staged, Path | None]] = []
    try:
        for sequence in sequences:
            final = target / sequence.name
            retired = None
            if final.exists():  # a sequence being replaced (or a stray folder not in the manifest)
                retired = work / f"retired-{sequence.name}"
                os.rename(final, retired)
            try:
                os.rename(sequence.path, final)
            except OSError:
                if retired is not None:
                    os.rename(retired, final)
                raise
            moved.append((sequence, retired))
            manifest["sequences"][sequence.name] = {"split": sequence.split, "scene": sequence.scene}
        write_json_atomically(target / MANIFEST, manifest)
    except BaseException:
        for sequence, retired in reversed(moved):
            os.rename(target / sequence.name, sequence.path)
            if retired is not None:
                os.rename(retired, target / sequence.name)
        raise


def ingest_archive(storage: Storage, archive: Path, work: Path, dataset_id: str, *, create: bool,
                   split: str = "train", replace: bool = False, max_unpacked_bytes: int,
                   max_pixels: int | None = None, layout: Layout | None = None,
                   notes: UploadNotes | None = None, max_decoded_bytes: int | None = None) -> DatasetDetail:
    """Unpack and validate an uploaded archive in ``work`` (a staging workspace), then store it; ``max_pixels`` and
    ``max_decoded_bytes``: every EXR's header is checked against them before any frame is decoded, in any layout
    (FrameTooLargeUpload).

    ``create``: make dataset ``dataset_id`` (UploadConflict if it exists), else add the archive's sequences
    to it (UnknownDataset if it does not exist; UploadConflict for taken names unless ``replace``).
    ``layout`` (other than ``denoiser``): the archive holds a renderer's sequence folders, converted first
    (``service.datasets.layouts``). Channels the format does not use are dropped either way; ``notes`` collects them
    and the conversion's warnings.
    """
    if split not in SPLITS:
        raise InvalidUpload("invalid_split", f"unknown split {split!r}; allowed: {', '.join(SPLITS)}")
    notes = UploadNotes() if notes is None else notes
    unpacked = work / "unpacked"
    unpack_archive(archive, unpacked, max_unpacked_bytes)
    archive.unlink()  # the unpacked copy is all we need; free the space early
    renderer_frames = layout is not None and layout.name != "denoiser"
    if max_pixels is not None:  # before the conversion or the stripping of unused channels decodes a frame
        check_unpacked_frame_pixels(unpacked, max_pixels, renderer_frames=renderer_frames,
                                    max_decoded_bytes=max_decoded_bytes)
    try:
        if renderer_frames:
            unpacked = import_renderer_folders(unpacked, _unwrap(unpacked), work / "imported", layout, split, notes)
        else:
            strip_unused_channels(unpacked, notes)
    except (DatasetError, FrameError) as error:
        raise _invalid(error, unpacked) from None
    sequences = find_sequences(unpacked, split, notes.ignored_files)
    with dataset_lock(storage, dataset_id):
        if create:
            _create_dataset(storage, dataset_id, sequences, work)
        else:
            if not dataset_exists(storage, dataset_id):
                raise UnknownDataset("not_found", f"dataset {dataset_id!r} does not exist")
            _add_to_dataset(storage, dataset_id, sequences, work, replace)
    return describe_dataset(storage, dataset_id)


def check_unpacked_frame_pixels(root: Path, max_pixels: int, *, renderer_frames: bool = False,
                                max_decoded_bytes: int | None = None) -> None:
    """FrameTooLargeUpload for the first EXR under ``root`` whose header declares more than ``max_pixels`` (or
    whose decode would take more than ``max_decoded_bytes``, ``model.io.exr.check_decoded_bytes``).

    ``renderer_frames`` (an upload in another renderer's layout): files in a ``references/`` folder are reference
    renders, at up to 2x the frames' resolution (``model.io.exr.check_declared_pixels``)."""
    for path in sorted(root.rglob("*.exr")):
        if path.is_file():
            try:
                check_frame_file_pixels(path, max_pixels, _relative(path, root),
                                        reference_render=renderer_frames and path.parent.name == REFERENCES_FOLDER,
                                        max_decoded_bytes=max_decoded_bytes)
            except FrameTooLarge as error:
                raise _too_many_pixels(error) from None
            except FrameError:
                continue  # unreadable: the full validation names the problem


def _too_many_pixels(error: FrameTooLarge) -> FrameTooLargeUpload:
    if isinstance(error, DecodeTooLarge):
        return FrameTooLargeUpload("frame_too_large", str(error), {"path": error.source, "decoded_bytes": error.pixels,
                                                                   "limit_bytes": error.limit})
    return FrameTooLargeUpload("frame_too_large", str(error), {"path": error.source, "pixels": error.pixels,
                                                               "limit_pixels": error.limit})
