"""Frame-by-frame uploads: frames staged one by one under ``staging/sequences/``, then committed as a sequence."""

from __future__ import annotations

import logging
import dataclasses
import json
import os
import shutil
import time
from pathlib import Path

from model.io.dataset import (
    DatasetError,
    MANIFEST,
    SEQUENCE_FORMAT,
    SPLITS,
    Sequence,
    frame_file_name,
    write_json_atomically,
)
from model.io.exr import FrameTooLarge, write_frame
from model.io.frames import FrameBundle, FrameError
from model.layouts import BUILTIN_LAYOUTS, Layout, read_layout_frame
from service.datasets.catalog import checked_dataset_id, checked_sequence_name, dataset_exists, describe_dataset
from service.datasets.errors import InvalidUpload, UnknownDataset, UploadConflict
from service.datasets.ingest import _Staged, _add_to_dataset, _create_dataset, _invalid, _too_many_pixels, frame_buffers
from service.datasets.layouts import UploadNotes
from service.datasets.descriptions import DatasetDetail, StagedSequence
from core.dataset_lock import dataset_lock, workspace
from core.storage import Storage

log = logging.getLogger("denoiser.datasets")


def _staged_paths(storage: Storage, dataset_id: str, sequence: str) -> tuple[Path, Path]:
    """(frames folder, state file) of a staged sequence: staging/sequences/<dataset>/<sequence>[.json]."""
    folder = storage.staging / "sequences" / checked_dataset_id(dataset_id) / checked_sequence_name(sequence)
    return folder, folder.with_name(f"{folder.name}.json")


def _load_state(state_file: Path, dataset_id: str, sequence: str) -> dict:
    if not state_file.is_file():
        raise UnknownDataset("not_found", f"no frames of sequence {sequence!r} are staged for dataset "
                                          f"{dataset_id!r}")
    return json.loads(state_file.read_text())


def _staged_info(dataset_id: str, state: dict) -> StagedSequence:
    return StagedSequence(dataset=dataset_id, sequence=state["sequence"], split=state["split"], scene=state["scene"],
                          frames=len(state["frames"]), next_frame_index=len(state["frames"]), width=state["width"],
                          height=state["height"], scales=state["scales"], buffers=state["buffers"])


def stage_frame(storage: Storage, dataset_id: str, sequence: str, upload: Path, *, split: str | None = None,
                scene: str | None = None, scales: list[int] | None = None,
                layout: Layout | None = None, notes: UploadNotes | None = None,
                max_pixels: int | None = None, max_decoded_bytes: int | None = None) -> StagedSequence:
    """Validate one uploaded frame EXR and append it to the staged sequence (the first frame starts it).

    The frame's ``frame_index`` must be the next one (0 first); resolution, reference scales and buffers must
    match the first frame; its ``sequence`` header must be empty or the sequence name. ``split`` and ``scene``
    are taken from the first frame's request (a later different split is refused); ``scales``, when given,
    are the reference scales every frame must have. ``layout`` (default ``denoiser``): how the EXR's channels map
    to the frame bundle; values are checked strictly, channels it does not use are dropped, and a frame without a
    frame index (or in another layout) is the next one; ``notes`` collects the channels dropped.
    """
    folder, state_file = _staged_paths(storage, dataset_id, sequence)
    if split is not None and split not in SPLITS:
        raise InvalidUpload("invalid_split", f"unknown split {split!r}; allowed: {', '.join(SPLITS)}")
    label = f"frame upload to {dataset_id}/{sequence}"
    layout = BUILTIN_LAYOUTS["denoiser"] if layout is None else layout
    try:
        read = read_layout_frame(upload, layout, mode="strict", max_pixels=max_pixels,
                                 max_decoded_bytes=max_decoded_bytes)
    except FrameTooLarge as error:
        raise _too_many_pixels(type(error)(label, error.problem, error.pixels, error.limit)) from None
    except FrameError as error:
        message = str(error).replace(str(upload), label)
        raise InvalidUpload("invalid_frame", message, {"buffer": error.buffer, "problem": error.problem}) from None
    frame = read.frame
    # The file as uploaded can be stored only when it is exactly the frame bundle the sequence needs.
    as_uploaded = layout.name == "denoiser" and not read.ignored_channels and read.frame_index_given
    if frame.sequence not in ("", sequence):
        raise InvalidUpload("invalid_frame", f"{label}: the frame's 'sequence' header says {frame.sequence!r}, not "
                            f"{sequence!r}; upload it to sequence {frame.sequence!r} or write it with sequence "
                            f"{sequence!r} (or none)")
    if scales is not None and list(frame.scales) != sorted(set(scales)):
        raise InvalidUpload("invalid_frame", f"{label}: reference scales {list(frame.scales)} are not the "
                                             f"requested {sorted(set(scales))}")
    buffers = frame_buffers(frame)
    with dataset_lock(storage, dataset_id):
        state = json.loads(state_file.read_text()) if state_file.is_file() else None
        expected = 0 if state is None else len(state["frames"])
        # Renderers number frames their own way (Blender from its timeline's start) or not at all: in another
        # layout, or without a frame index, the uploaded frame is the next one.
        if not read.frame_index_given or layout.name != "denoiser":
            frame = dataclasses.replace(frame, frame_index=expected)
        if frame.frame_index != expected:
            raise UploadConflict("frame_out_of_order", f"{label}: frame_index is {frame.frame_index}, expected "
                                                       f"{expected} (frames are uploaded in order from 0)",
                                 {"expected": expected, "received": frame.frame_index})
        if state is None:
            state = {"sequence": sequence, "split": split or "train", "scene": scene, "width": frame.width,
                     "height": frame.height, "scales": list(frame.scales), "buffers": buffers, "frames": []}
            folder.mkdir(parents=True, exist_ok=True)
        else:
            _check_continues(state, frame, buffers, split, label)
        file = frame_file_name(expected)
        if frame.sequence == sequence and as_uploaded:
            os.replace(upload, folder / file)  # already exactly what the stored sequence needs
        else:
            # The header must name the sequence (Sequence checks it), and the file hold the frame bundle only:
            # write the frame again with it filled in.
            write_frame(folder / file, dataclasses.replace(frame, sequence=sequence))
        state["frames"].append({"index": expected, "file": file, "camera_cut": bool(frame.camera_cut)})
        write_json_atomically(state_file, state)
    if notes is not None:
        notes.ignored_channels.update(read.ignored_channels)
    return _staged_info(dataset_id, state)


def expire_staged_uploads(storage: Storage, ttl_seconds: float, now: float | None = None) -> list[str]:
    """Discard frame-by-frame uploads untouched for ``ttl_seconds`` (their state file's modification time: every
    staged frame rewrites it); returns "dataset/sequence" of each one discarded."""
    now = time.time() if now is None else now
    root = storage.staging / "sequences"
    expired = []
    for state_file in sorted(root.glob("*/*.json")) if root.is_dir() else []:
        dataset_id, sequence = state_file.parent.name, state_file.stem
        try:
            if now - state_file.stat().st_mtime < ttl_seconds:
                continue
            with dataset_lock(storage, dataset_id):
                if not state_file.is_file() or now - state_file.stat().st_mtime < ttl_seconds:
                    continue  # committed, discarded or continued meanwhile
                state_file.unlink()
                shutil.rmtree(state_file.with_suffix(""), ignore_errors=True)
        except (OSError, InvalidUpload):  # gone meanwhile, or a name this code never wrote
            continue
        expired.append(f"{dataset_id}/{sequence}")
        log.info("discarded the frame upload %s/%s: untouched for %s s", dataset_id, sequence, ttl_seconds)
    return expired


def _check_continues(state: dict, frame: FrameBundle, buffers: list[str], split: str | None, label: str) -> None:
    first = "the first frame's"
    if (frame.width, frame.height) != (state["width"], state["height"]):
        raise InvalidUpload("invalid_frame", f"{label}: resolution {frame.width}x{frame.height} differs from "
                                             f"{first} {state['width']}x{state['height']}")
    if list(frame.scales) != state["scales"]:
        raise InvalidUpload("invalid_frame", f"{label}: reference scales {list(frame.scales)} differ from "
                                             f"{first} {state['scales']}")
    if buffers != state["buffers"]:
        raise InvalidUpload("invalid_frame", f"{label}: buffers {', '.join(buffers)} differ from {first} "
                                             f"{', '.join(state['buffers'])}")
    if split is not None and split != state["split"]:
        raise UploadConflict("split_mismatch", f"{label}: split {split!r} differs from {state['split']!r}, given "
                                               f"with the first frame")


def staged_sequence(storage: Storage, dataset_id: str, sequence: str) -> StagedSequence:
    _, state_file = _staged_paths(storage, dataset_id, sequence)
    return _staged_info(dataset_id, _load_state(state_file, dataset_id, sequence))


def discard_staged_sequence(storage: Storage, dataset_id: str, sequence: str) -> None:
    folder, state_file = _staged_paths(storage, dataset_id, sequence)
    _load_state(state_file, dataset_id, sequence)  # 404 before a lock file is made for an unknown id
    with dataset_lock(storage, dataset_id):
        _load_state(state_file, dataset_id, sequence)
        state_file.unlink()
        shutil.rmtree(folder, ignore_errors=True)


def commit_staged_sequence(storage: Storage, dataset_id: str, sequence: str, *, replace: bool = False
                           ) -> DatasetDetail:
    """Write the staged sequence's manifest, check it, and move it into the dataset (created if new)."""
    folder, state_file = _staged_paths(storage, dataset_id, sequence)
    _load_state(state_file, dataset_id, sequence)  # 404 before a lock file is made for an unknown id
    with dataset_lock(storage, dataset_id), workspace(storage, "commit") as work:
        state = _load_state(state_file, dataset_id, sequence)
        frames = state["frames"]
        if [entry["index"] for entry in frames] != list(range(len(frames))) or not frames:
            raise InvalidUpload("invalid_dataset", f"staged sequence {sequence!r} has frames "
                                                   f"{[e['index'] for e in frames]}, not 0..n-1")
        manifest = {"format": SEQUENCE_FORMAT, "sequence": sequence, "scene": state["scene"],
                    "width": state["width"], "height": state["height"], "scales": state["scales"],
                    "frames": frames, "metadata": {"uploaded": "frame by frame"}}
        write_json_atomically(folder / MANIFEST, manifest)
        try:
            Sequence(folder)  # every listed frame file is there and the manifest is well-formed
        except DatasetError as error:
            (folder / MANIFEST).unlink(missing_ok=True)
            raise _invalid(error, folder.parent) from None
        staged = [_Staged(sequence, folder, state["split"], state["scene"])]
        try:
            if dataset_exists(storage, dataset_id):
                _add_to_dataset(storage, dataset_id, staged, work, replace)
            else:
                _create_dataset(storage, dataset_id, staged, work)
        except BaseException:
            if folder.is_dir():  # not moved: the staged frames stay for another try (e.g. with replace=true)
                (folder / MANIFEST).unlink(missing_ok=True)
            raise
        state_file.unlink()
    return describe_dataset(storage, dataset_id)
