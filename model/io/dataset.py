"""Sequences and datasets on disk.

A sequence is a folder of ``frame_%04d.exr`` files (one frame bundle each, see ``model.io.exr``) plus
``manifest.json``::

    {"format": "denoiser-sequence/1", "sequence": name, "scene": recipe name or null,
     "width": W, "height": H, "scales": [reference scales], "frames": [{"index", "file", "camera_cut"}],
     "metadata": {free-form, e.g. renderer settings}}

Frame ``i`` of a sequence has ``frame_index == i``, so positions and frame indices are the same numbers.

A dataset is a folder of sequence folders plus ``manifest.json``::

    {"format": "denoiser-dataset/1", "sequences": {name: {"split": "train" | "validation" | "test",
                                                          "scene": recipe name or null}}}

Folders appear complete or not at all: ``SequenceWriter`` renders into a hidden temporary folder and
renames it into place, and manifests are replaced with ``os.replace``. A dataset's manifest is changed only under
an exclusive ``flock`` on its folder, re-read first, so processes adding sequences to one dataset at once keep
each other's.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import json
import os
import shutil
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from model.io.exr import read_frame, write_frame
from model.io.frames import FrameBundle, validate_frame
from model.names import SPLITS

SEQUENCE_FORMAT = "denoiser-sequence/1"
DATASET_FORMAT = "denoiser-dataset/1"
MANIFEST = "manifest.json"


class DatasetError(ValueError):
    """A sequence or dataset on disk (or being written) breaks the format; the message names file and field."""


def frame_file_name(index: int) -> str:
    return f"frame_{index:04d}.exr"


def _check_split(split: str) -> str:
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; allowed: {', '.join(SPLITS)}")
    return split


def _check_folder_name(name: str, what: str) -> str:
    # Names become folder and file names under a root the service controls: no paths, no hidden names.
    plain = isinstance(name, str) and name and Path(name).name == name and "\\" not in name
    if not plain or name.startswith("."):
        raise DatasetError(f"{what} {name!r} is not a plain folder name")
    return name


def write_json_atomically(path: Path, content: dict) -> None:
    """Write ``content`` as indented JSON under a temporary name beside ``path``, then rename it over ``path``:
    readers see the old file or the new one, never half of one."""
    temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        temporary.write_text(json.dumps(content, indent=2) + "\n")
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def json_problem(error: ValueError | RecursionError) -> str:
    """What is wrong with JSON text that ``json.loads`` refused, in words. Besides syntax errors it raises
    RecursionError for deep nesting (``[`` x 100000) and ValueError for integers past Python's 4300 digits."""
    if isinstance(error, RecursionError):
        return "not valid JSON here (nested too deeply)"
    if isinstance(error, json.JSONDecodeError):
        return f"not valid JSON ({error})"
    if isinstance(error, UnicodeDecodeError):
        return f"not UTF-8 text ({error})"
    return f"not valid JSON here ({error})"  # e.g. an integer with too many digits


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise DatasetError(f"{path}: not found (is {path.parent} a {what} folder?)")
    try:
        content = json.loads(path.read_text())
    except (ValueError, RecursionError) as error:
        raise DatasetError(f"{path}: {json_problem(error)}") from None
    if not isinstance(content, dict):
        raise DatasetError(f"{path}: top level is a {type(content).__name__}, not an object")
    return content


def _field(manifest: dict, key: str, types: type | tuple[type, ...], path: Path, description: str) -> Any:
    if key not in manifest:
        raise DatasetError(f"{path}: field '{key}' is missing")
    value = manifest[key]
    # bool is an int in Python; a boolean width or index is still a mistake.
    if not isinstance(value, types) or (isinstance(value, bool) and bool not in _as_tuple(types)):
        raise DatasetError(f"{path}: field '{key}' is {value!r}, not {description}")
    return value


def _as_tuple(types: type | tuple[type, ...]) -> tuple[type, ...]:
    return types if isinstance(types, tuple) else (types,)


def _read_manifest(path: Path, what: str, expected_format: str) -> dict:
    """A ``what`` ("sequence", "dataset") folder's manifest, refused unless it declares ``expected_format``."""
    manifest = _read_json(path, what)
    found = manifest.get("format")
    if found != expected_format:
        raise DatasetError(f"{path}: field 'format' is {found!r}, expected {expected_format!r}")
    return manifest


class Sequence:
    """A sequence folder opened for reading; frames are read from disk when indexed."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.manifest_path = self.path / MANIFEST
        manifest = _read_manifest(self.manifest_path, "sequence", SEQUENCE_FORMAT)
        where = self.manifest_path
        self.name: str = _field(manifest, "sequence", str, where, "a string")
        self.scene: str | None = _field(manifest, "scene", (str, type(None)), where, "a string or null")
        self.width: int = _field(manifest, "width", int, where, "an integer")
        self.height: int = _field(manifest, "height", int, where, "an integer")
        if self.width < 1 or self.height < 1:
            raise DatasetError(f"{where}: resolution {self.width}x{self.height} has no pixels")
        self.scales: tuple[int, ...] = self._checked_scales(_field(manifest, "scales", list, where, "a list"))
        self.metadata: dict = _field(manifest, "metadata", dict, where, "an object")
        self._frames = self._checked_frames(_field(manifest, "frames", list, where, "a list"))

    def _checked_scales(self, scales: list) -> tuple[int, ...]:
        for scale in scales:
            if not isinstance(scale, int) or isinstance(scale, bool) or scale < 1:
                raise DatasetError(f"{self.manifest_path}: field 'scales' holds {scale!r}, not a positive integer")
        if sorted(set(scales)) != scales:
            raise DatasetError(f"{self.manifest_path}: field 'scales' {scales} is not ascending without repeats")
        return tuple(scales)

    def _checked_frames(self, frames: list) -> list[dict]:
        if not frames:
            raise DatasetError(f"{self.manifest_path}: field 'frames' is empty")
        for position, entry in enumerate(frames):
            where = f"{self.manifest_path}: frames[{position}]"
            if not isinstance(entry, dict):
                raise DatasetError(f"{where} is {entry!r}, not an object")
            index = entry.get("index")
            if not isinstance(index, int) or isinstance(index, bool) or index != position:
                raise DatasetError(f"{where}: field 'index' is {index!r}, expected {position} (frames count from 0)")
            file = entry.get("file")
            if not isinstance(file, str) or Path(file).name != file or file in {"", ".", ".."}:
                raise DatasetError(f"{where}: field 'file' is {file!r}, not a file name inside the sequence folder")
            if not (self.path / file).is_file():
                raise DatasetError(f"{where}: field 'file': {self.path / file} does not exist")
            if not isinstance(entry.get("camera_cut"), bool):
                raise DatasetError(f"{where}: field 'camera_cut' is {entry.get('camera_cut')!r}, not true or false")
        return frames

    @property
    def cuts(self) -> list[int]:
        """Frame indices that start after a camera cut (history must be dropped there)."""
        return [entry["index"] for entry in self._frames if entry["camera_cut"]]

    def frame_path(self, index: int) -> Path:
        return self.path / self._frames[index]["file"]

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, index: int) -> FrameBundle:
        if not -len(self) <= index < len(self):
            raise IndexError(f"sequence '{self.name}' has {len(self)} frames; index {index} is out of range")
        entry = self._frames[index]
        frame = read_frame(self.frame_path(index))
        self._check_frame_matches_manifest(frame, entry)
        return frame

    def __iter__(self) -> Iterator[FrameBundle]:
        for index in range(len(self)):
            yield self[index]

    def _check_frame_matches_manifest(self, frame: FrameBundle, entry: dict) -> None:
        path = self.path / entry["file"]
        expected = {
            "resolution": (self.width, self.height),
            "scales": self.scales,
            "frame_index": entry["index"],
            "camera_cut": entry["camera_cut"],
            "sequence": self.name,
        }
        found = {
            "resolution": frame.resolution,
            "scales": frame.scales,
            "frame_index": frame.frame_index,
            "camera_cut": frame.camera_cut,
            "sequence": frame.sequence,
        }
        for key in expected:
            if expected[key] != found[key]:
                raise DatasetError(f"{path}: {key} is {found[key]!r} but {self.manifest_path} says {expected[key]!r}")

    def __repr__(self) -> str:
        size = f"{self.width}x{self.height}"
        return f"Sequence({str(self.path)!r}, frames={len(self)}, {size}, scales={list(self.scales)})"


class SequenceWriter:
    """Writes a sequence folder that appears complete or not at all.

    Frames go into a hidden temporary folder next to ``path`` as they are added; a clean exit writes the
    manifest and renames the folder into place, an exception deletes it and leaves ``path`` as it was::

        with SequenceWriter(root / "kitchen_0", "kitchen_0", scene="kitchen") as writer:
            for frame in render(...):
                writer.add(frame)
    """

    def __init__(
        self,
        path: str | os.PathLike,
        name: str,
        *,
        scene: str | None = None,
        metadata: dict | None = None,
        half: bool = False,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
        self.name = name
        self.scene = scene
        self.metadata = dict(metadata or {})
        self.half = half
        self.overwrite = overwrite
        self._temporary: Path | None = None
        self._frames: list[dict] = []
        self._resolution: tuple[int, int] | None = None
        self._scales: tuple[int, ...] = ()

    def __enter__(self) -> SequenceWriter:
        # Fail before anything is rendered: an existing target and unserializable metadata are both known now.
        if self.path.exists() and not self.overwrite:
            raise FileExistsError(f"{self.path} already exists; pass overwrite=True to replace it")
        if not isinstance(self.name, str) or not self.name:
            raise DatasetError(f"sequence name {self.name!r} is not a non-empty string")
        try:
            json.dumps(self.metadata)
        except (TypeError, ValueError) as error:
            raise DatasetError(f"metadata for sequence '{self.name}' is not JSON-serializable ({error})") from None
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._temporary = self.path.with_name(f".{self.path.name}.{uuid.uuid4().hex[:8]}.partial")
        self._temporary.mkdir()
        return self

    def add(self, frame: FrameBundle) -> Path:
        """Validate and write the next frame; it must continue the sequence (index, resolution, scales)."""
        if self._temporary is None:
            raise RuntimeError("SequenceWriter.add called outside its 'with' block")
        position = len(self._frames)
        file = frame_file_name(position)
        frame = validate_frame(frame, str(self.path / file))
        self._check_continues_sequence(frame, position)
        if not frame.sequence:
            # Each file names its sequence in its header; fill it in rather than store "".
            frame = dataclasses.replace(frame, sequence=self.name)
        write_frame(self._temporary / file, frame, half=self.half)
        if position == 0:
            self._resolution, self._scales = frame.resolution, frame.scales
        self._frames.append({"index": position, "file": file, "camera_cut": bool(frame.camera_cut)})
        return self.path / file

    def _check_continues_sequence(self, frame: FrameBundle, position: int) -> None:
        where = f"sequence '{self.name}', frame {position}"
        if frame.frame_index != position:
            raise DatasetError(f"{where}: frame_index is {frame.frame_index}, expected {position} (consecutive from 0)")
        if frame.sequence and frame.sequence != self.name:
            raise DatasetError(f"{where}: frame belongs to sequence '{frame.sequence}'")
        if position == 0:
            return
        if frame.resolution != self._resolution:
            raise DatasetError(
                f"{where}: resolution {frame.width}x{frame.height} differs from the first frame's "
                f"{self._resolution[0]}x{self._resolution[1]}"
            )
        if frame.scales != self._scales:
            raise DatasetError(
                f"{where}: reference scales {list(frame.scales)} differ from the first frame's {list(self._scales)}"
            )

    def __exit__(self, exc_type, exc, traceback) -> bool:
        temporary, self._temporary = self._temporary, None
        if temporary is None:
            return False
        try:
            if exc_type is None:
                self._finish(temporary)
        finally:
            shutil.rmtree(temporary, ignore_errors=True)  # gone already after a successful rename
        return False

    def _finish(self, temporary: Path) -> None:
        if not self._frames:
            raise DatasetError(f"sequence '{self.name}' has no frames; nothing written to {self.path}")
        width, height = self._resolution
        manifest = {
            "format": SEQUENCE_FORMAT,
            "sequence": self.name,
            "scene": self.scene,
            "width": width,
            "height": height,
            "scales": list(self._scales),
            "frames": self._frames,
            "metadata": self.metadata,
        }
        write_json_atomically(temporary / MANIFEST, manifest)
        _move_folder_into_place(temporary, self.path, self.overwrite)


def _move_folder_into_place(source: Path, target: Path, overwrite: bool) -> None:
    """Rename ``source`` to ``target``; an existing target (overwrite=True) is swapped out, then deleted.

    Each rename is atomic; between the two renames of a swap ``target`` briefly does not exist, but it is
    never partly written. A failed second rename puts the old folder back.
    """
    if not target.exists():
        os.rename(source, target)
        return
    if not overwrite:
        raise FileExistsError(f"{target} appeared while the sequence was being written; not replacing it")
    retired = target.with_name(f".{target.name}.{uuid.uuid4().hex[:8]}.old")
    os.rename(target, retired)
    try:
        os.rename(source, target)
    except OSError:
        os.rename(retired, target)
        raise
    shutil.rmtree(retired, ignore_errors=True)


@contextlib.contextmanager
def _manifest_lock(root: Path) -> Iterator[None]:
    """Exclusive lock on ``root``'s dataset manifest, between processes: ``flock`` on the dataset folder itself (the
    manifest is replaced by a rename, so it cannot hold the lock, and a lock file would be one more file in it)."""
    root.mkdir(parents=True, exist_ok=True)
    folder = os.open(root, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(folder, fcntl.LOCK_EX)
        yield
    finally:
        os.close(folder)  # closing the last descriptor releases the lock


class Dataset:
    """A folder of sequence folders with a manifest assigning each sequence a split."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)
        self.manifest_path = self.root / MANIFEST
        self._entries: dict[str, dict] = self._read_entries()

    def _read_entries(self) -> dict[str, dict]:
        manifest = _read_manifest(self.manifest_path, "dataset", DATASET_FORMAT)
        entries = _field(manifest, "sequences", dict, self.manifest_path, "an object")
        checked: dict[str, dict] = {}
        for name, entry in entries.items():
            where = f"{self.manifest_path}: sequences['{name}']"
            if not isinstance(entry, dict):
                raise DatasetError(f"{where} is {entry!r}, not an object")
            if entry.get("split") not in SPLITS:
                raise DatasetError(f"{where}: field 'split' is {entry.get('split')!r}, not one of {', '.join(SPLITS)}")
            if not isinstance(entry.get("scene"), (str, type(None))):
                raise DatasetError(f"{where}: field 'scene' is {entry.get('scene')!r}, not a string or null")
            if not (self.root / name).is_dir():
                raise DatasetError(f"{where}: folder {self.root / name} does not exist")
            checked[name] = {"split": entry["split"], "scene": entry["scene"]}
        return checked

    @classmethod
    def create(cls, root: str | os.PathLike) -> Dataset:
        """Make an empty dataset at ``root`` (the folder may exist, but must not hold a manifest yet)."""
        root = Path(root)
        if not cls._made_empty(root):
            raise FileExistsError(f"{root / MANIFEST} already exists; open it with Dataset({str(root)!r})")
        return cls(root)

    @classmethod
    def open_or_create(cls, root: str | os.PathLike) -> Dataset:
        """The dataset at ``root``, made empty first if it has no manifest (one check-and-create under the lock, so
        processes starting on the same new folder at once share one dataset)."""
        root = Path(root)
        cls._made_empty(root)
        return cls(root)

    @staticmethod
    def _made_empty(root: Path) -> bool:
        """Write an empty manifest at ``root`` unless one exists (checked and written under the lock); whether it
        did."""
        with _manifest_lock(root):
            if (root / MANIFEST).exists():
                return False
            write_json_atomically(root / MANIFEST, {"format": DATASET_FORMAT, "sequences": {}})
            return True

    def names(self, split: str | None = None) -> list[str]:
        if split is not None:
            _check_split(split)
        return sorted(name for name, entry in self._entries.items() if split is None or entry["split"] == split)

    def split_of(self, name: str) -> str:
        return self._entry(name)["split"]

    def sequence(self, name: str) -> Sequence:
        self._entry(name)
        return Sequence(self.root / name)

    def sequences(self, split: str | None = None) -> list[Sequence]:
        """The sequences of one split (all when None), by name."""
        return [Sequence(self.root / name) for name in self.names(split)]

    def add_sequence_dir(self, name: str, split: str, *, replace: bool = False) -> Sequence:
        """Register the sequence folder ``root/name`` (already written there) under ``split``.

        ``replace`` re-registers a name that is already known (its folder was overwritten).
        """
        _check_split(split)
        _check_folder_name(name, "sequence folder")
        sequence = Sequence(self.root / name)  # checks the folder is a well-formed sequence
        with self._changing() as entries:
            if name in entries and not replace:
                raise DatasetError(f"{self.manifest_path}: sequence '{name}' is already registered")
            entries[name] = {"split": split, "scene": sequence.scene}
        return sequence

    def set_split(self, name: str, split: str) -> None:
        _check_split(split)
        with self._changing() as entries:
            if name not in entries:
                raise DatasetError(f"{self.manifest_path}: no sequence named '{name}'")
            entries[name]["split"] = split

    def summary(self) -> dict[str, dict]:
        """Per split: sequence count, scenes, frame count, resolutions [[w, h], ...] and reference scales.

        Reads only manifests, never frames.
        """
        summary = {}
        for split in SPLITS:
            sequences = self.sequences(split)
            resolutions = sorted({(s.width, s.height) for s in sequences})
            summary[split] = {
                "sequences": len(sequences),
                "scenes": sorted({s.scene for s in sequences if s.scene is not None}),
                "frames": sum(len(s) for s in sequences),
                "resolutions": [[width, height] for width, height in resolutions],
                "scales": sorted({scale for s in sequences for scale in s.scales}),
            }
        return summary

    def format_summary(self) -> str:
        """The summary as an aligned text table, one row per split."""
        header = ("split", "sequences", "frames", "resolutions", "scales", "scenes")
        rows = [header]
        for split, entry in self.summary().items():
            rows.append((
                split,
                str(entry["sequences"]),
                str(entry["frames"]),
                ", ".join(f"{w}x{h}" for w, h in entry["resolutions"]) or "-",
                ", ".join(str(s) for s in entry["scales"]) or "-",
                ", ".join(entry["scenes"]) or "-",
            ))
        widths = [max(len(row[column]) for row in rows) for column in range(len(header))]
        numeric = {1, 2}
        lines = [
            "  ".join(cell.rjust(w) if c in numeric else cell.ljust(w) for c, (cell, w) in enumerate(zip(row, widths)))
            for row in rows
        ]
        return f"dataset {self.root}\n" + "\n".join(line.rstrip() for line in lines)

    def _entry(self, name: str) -> dict:
        try:
            return self._entries[name]
        except KeyError:
            raise DatasetError(f"{self.manifest_path}: no sequence named '{name}'") from None

    @contextlib.contextmanager
    def _changing(self) -> Iterator[dict[str, dict]]:
        """The manifest's entries as stored now, under the dataset's lock; written back when the block ends without
        an error. Processes that add sequences to one dataset at once (two imports, two generators) each change the
        manifest they read under the lock, so none drops another's sequence."""
        with _manifest_lock(self.root):
            entries = self._read_entries()
            yield entries
            write_json_atomically(self.manifest_path, {"format": DATASET_FORMAT, "sequences": entries})
        self._entries = entries

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r}, sequences={len(self)})"


def dataset_digest(root: str | os.PathLike) -> str:
    """sha256 over a dataset's manifest and its sequences' manifests (names, splits, frames, renderer settings):
    what a training run's lineage and a pretrained model's manifest record as the dataset's identity."""
    import hashlib

    root = Path(root)
    digest = hashlib.sha256((root / MANIFEST).read_bytes())
    dataset = Dataset(root)
    for split in SPLITS:
        for name in dataset.names(split):
            digest.update(f"{split}/{name}\n".encode())
            digest.update((root / name / MANIFEST).read_bytes())
    return digest.hexdigest()
