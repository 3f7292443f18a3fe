"""Stored datasets: archive uploads, frame-by-frame uploads, inspection and deletion (no HTTP here).

Every upload is received into its own folder under ``staging/``, unpacked and validated there (every frame
read with ``model.exr.read_frame`` and checked against its sequence manifest by ``model.dataset.Sequence``),
and only then moved into ``datasets/<id>`` with ``os.rename``. So a failed upload leaves nothing behind, and an
upload that adds sequences to an existing dataset either adds all of them or none:

- a new dataset is assembled completely in staging (manifest included) and renamed into place in one step;
- sequences added to an existing dataset are renamed in one by one, then the dataset manifest is replaced
  atomically; a failure on the way renames every moved folder back (and restores replaced ones).

Changes to one dataset are serialized by a lock file (``staging/locks/<id>.lock``, ``flock``), which works
across threads and across API processes sharing the data folder.

Archive members are extracted by hand, never with ``extractall``: absolute paths, ``..``, links and device
files are refused with an error naming the member, and the unpacked size is bounded (against zip bombs).

Errors are ``UploadError`` subclasses; each maps to one HTTP status in the routes (``service.routes.datasets``).
"""

from __future__ import annotations

import dataclasses
import errno
import fcntl
import json
import logging
import os
import re
import shutil
import stat
import tarfile
import time
import uuid
import zipfile
import zlib
from collections.abc import AsyncIterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Literal

import OpenEXR

from model.dataset import (
    DATASET_FORMAT,
    MANIFEST,
    SEQUENCE_FORMAT,
    SPLITS,
    Dataset,
    DatasetError,
    Sequence,
    frame_file_name,
    json_problem,
    write_json_atomically,
)
from model.exr import CHANNEL_SLOTS, FrameTooLarge, check_frame_file_pixels, write_frame
from model.frames import BUFFERS, FrameBundle, FrameError
from model.importer import REFERENCES_FOLDER
from model.layouts import BUILTIN_LAYOUTS, Layout, read_layout_frame
from service.schemas import DatasetDetail, DatasetSummary, SequenceInfo, SplitSummary, StagedSequence
from service.storage import Storage, checked_id
from service.upload_layouts import UploadNotes, import_renderer_folders, strip_unused_channels

log = logging.getLogger("denoiser.datasets")

ArchiveKind = Literal["zip", "tar", "tar.gz"]

CHUNK_BYTES = 1024 * 1024
MAX_ARCHIVE_MEMBERS = 100_000
# Files that archivers on macOS add; they are dropped rather than refused.
_IGNORED_FOLDERS = {"__MACOSX"}
_IGNORED_FILES = {".DS_Store", "Thumbs.db"}


# --- errors ------------------------------------------------------------------------------------------------


class UploadError(Exception):
    """A caller's mistake; ``code`` is the machine-readable error code, ``details`` extra JSON."""

    def __init__(self, code: str, message: str, details: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.details = details


class InvalidUpload(UploadError):
    """The uploaded bytes are wrong: not an archive, unsafe members, bad layout, invalid frames."""


class UploadTooLarge(UploadError):
    """The upload, or what it unpacks to, exceeds the configured limit."""


class FrameTooLargeUpload(UploadError):
    """A frame's header declares more pixels than the limit (refused before its pixels are decoded)."""


class UnknownDataset(UploadError):
    """No such dataset or staged sequence."""


class UploadConflict(UploadError):
    """The upload clashes with stored state: a dataset id or sequence name taken, a frame out of order."""


# --- receiving ---------------------------------------------------------------------------------------------


async def save_stream(chunks: AsyncIterable[bytes], destination: Path, limit: int, what: str,
                      declared_length: str | None = None) -> int:
    """Write an async stream of byte chunks to ``destination``; UploadTooLarge once it passes ``limit`` bytes.

    ``declared_length`` (the Content-Length header) lets an oversized upload fail before any byte is read.
    The partial file is removed on any failure. Writes are plain blocking writes of one chunk each (tens of
    kilobytes into the page cache), cheap enough not to need a thread.
    """
    if declared_length is not None and declared_length.isdigit() and int(declared_length) > limit:
        raise _too_large(what, int(declared_length), limit)
    received = 0
    try:
        with destination.open("wb") as file:
            async for chunk in chunks:
                received += len(chunk)
                if received > limit:
                    raise _too_large(what, received, limit, at_least=True)
                file.write(chunk)
    except BaseException:
        destination.unlink(missing_ok=True)
        raise
    if received == 0:
        destination.unlink(missing_ok=True)
        raise InvalidUpload("empty_body", f"the {what} is empty")
    return received


def _too_large(what: str, size: int, limit: int, at_least: bool = False) -> UploadTooLarge:
    amount = f"at least {size}" if at_least else str(size)
    return UploadTooLarge("payload_too_large", f"the {what} is {amount} bytes; the limit is {limit} bytes",
                          {"limit_bytes": limit})


# --- staging workspaces and locks --------------------------------------------------------------------------


@contextmanager
def workspace(storage: Storage, purpose: str) -> Iterator[Path]:
    """A fresh folder under staging/, deleted on exit whatever happened (committed data was moved out)."""
    folder = storage.staging_folder(f"{purpose}-{uuid.uuid4().hex}")
    folder.mkdir(parents=True)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@contextmanager
def dataset_lock(storage: Storage, dataset_id: str) -> Iterator[None]:
    """Exclusive lock on one dataset id (its stored folder and its staged frame uploads)."""
    folder = storage.staging / "locks"
    folder.mkdir(parents=True, exist_ok=True)
    with (folder / f"{checked_id(dataset_id, 'dataset id')}.lock").open("a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def checked_dataset_id(dataset_id: str) -> str:
    return _checked_name(dataset_id, "dataset id")


def checked_sequence_name(name: str) -> str:
    return _checked_name(name, "sequence name")


def _checked_name(value: str, what: str) -> str:
    try:
        return checked_id(value, what)
    except ValueError as error:
        raise InvalidUpload("invalid_name", str(error)) from None


def new_dataset_id(name: str | None) -> str:
    """The given name (a valid id) or, without one, "dataset-" plus a short random suffix."""
    if name is not None:
        return checked_dataset_id(name)
    return f"dataset-{uuid.uuid4().hex[:8]}"


# --- archives ----------------------------------------------------------------------------------------------


def sniff_archive(path: Path) -> ArchiveKind:
    """zip, tar or tar.gz by magic bytes (the Content-Type header is not trusted)."""
    with path.open("rb") as file:
        head = file.read(512)
    if head[:4] in (b"PK\x03\x04", b"PK\x05\x06"):
        return "zip"
    if head[:2] == b"\x1f\x8b":
        return "tar.gz"
    if head[257:262] == b"ustar":
        return "tar"
    raise InvalidUpload("invalid_archive", f"the upload is not a zip, tar or tar.gz archive "
                                           f"(first bytes {head[:8].hex(' ')})")


def unpacked_limit(archive_bytes: int, *, max_bytes: int, max_ratio: float, exempt_bytes: int) -> int:
    """The most bytes an archive of ``archive_bytes`` may unpack to: ``max_ratio`` times its size (at least
    ``exempt_bytes``), and never more than ``max_bytes``. Frame EXRs barely compress further, so a legitimate
    archive stays near 1:1 while a zip bomb (1000:1 and more) is stopped after a few megabytes."""
    return min(max_bytes, max(exempt_bytes, int(max_ratio * archive_bytes)))


def unpack_archive(archive: Path, destination: Path, max_bytes: int) -> ArchiveKind:
    """Extract ``archive`` into ``destination`` member by member, refusing anything unsafe; return its kind."""
    kind = sniff_archive(archive)
    extractor = _Extractor(destination, max_bytes)
    try:
        if kind == "zip":
            _unpack_zip(archive, extractor)
        else:
            _unpack_tar(archive, "r:gz" if kind == "tar.gz" else "r:", extractor)
    # Corrupt or truncated archives surface as any of these from zipfile, tarfile, gzip and zlib.
    except (zipfile.BadZipFile, tarfile.TarError, zlib.error, EOFError, NotImplementedError) as error:
        raise InvalidUpload("invalid_archive", f"the {kind} archive is corrupt or truncated "
                                               f"({type(error).__name__}: {error})") from None
    except OSError as error:
        if error.errno is not None:  # a real I/O problem on our side, not bad input
            raise
        raise InvalidUpload("invalid_archive", f"the {kind} archive is corrupt or truncated ({error})") from None
    if extractor.files == 0:
        raise InvalidUpload("invalid_archive", f"the {kind} archive holds no files")
    return kind


class _Extractor:
    """Writes checked archive members under one folder, counting members and bytes."""

    def __init__(self, root: Path, max_bytes: int) -> None:
        self.root = root
        self.max_bytes = max_bytes
        self.written = 0
        self.files = 0
        self.members = 0
        self.seen: set[tuple[str, ...]] = set()
        root.mkdir(parents=True, exist_ok=True)

    def parts(self, name: str) -> tuple[str, ...] | None:
        """The member's path components, or None for a member to skip; InvalidUpload for an unsafe name."""
        self.members += 1
        if self.members > MAX_ARCHIVE_MEMBERS:
            raise UploadTooLarge("payload_too_large", f"the archive has more than {MAX_ARCHIVE_MEMBERS} members",
                                 {"limit_members": MAX_ARCHIVE_MEMBERS})
        if name.startswith("/") or "\\" in name or re.match(r"^[A-Za-z]:", name) or "\x00" in name:
            raise InvalidUpload("unsafe_archive_member", f"archive member {name!r} has an absolute or "
                                                         f"non-portable path", {"member": name})
        parts = tuple(part for part in name.split("/") if part not in ("", "."))
        if ".." in parts:
            raise InvalidUpload("unsafe_archive_member", f"archive member {name!r} points outside the archive "
                                                         f"('..' in its path)", {"member": name})
        if not parts or any(part in _IGNORED_FOLDERS for part in parts) or parts[-1] in _IGNORED_FILES \
                or parts[-1].startswith("._"):
            return None
        return parts

    def directory(self, parts: tuple[str, ...], name: str) -> None:
        target = self._target(parts, name)
        if target.exists() and not target.is_dir():
            raise InvalidUpload("invalid_archive", f"archive member {name!r} is both a file and a folder",
                                {"member": name})
        target.mkdir(parents=True, exist_ok=True)

    def file(self, parts: tuple[str, ...], name: str, source: BinaryIO) -> None:
        if parts in self.seen:
            raise InvalidUpload("invalid_archive", f"archive member {name!r} appears twice", {"member": name})
        self.seen.add(parts)
        target = self._target(parts, name)
        if target.exists():
            raise InvalidUpload("invalid_archive", f"archive member {name!r} is both a file and a folder",
                                {"member": name})
        target.parent.mkdir(parents=True, exist_ok=True)
        with target.open("wb") as out:
            while chunk := source.read(CHUNK_BYTES):
                self.written += len(chunk)
                if self.written > self.max_bytes:
                    raise self.too_large("unpacks to more")  # "... than N bytes"
                out.write(chunk)
        self.files += 1

    def too_large(self, what: str) -> UploadTooLarge:
        return UploadTooLarge("payload_too_large", f"the archive {what} than {self.max_bytes} bytes, the most "
                                                   f"this upload may unpack to (limits on the unpacked size and "
                                                   f"on the compression ratio)", {"limit_bytes": self.max_bytes})

    def _target(self, parts: tuple[str, ...], name: str) -> Path:
        # A file member earlier in the archive may sit where this member needs a folder.
        for depth in range(1, len(parts)):
            if (self.root.joinpath(*parts[:depth])).is_file():
                raise InvalidUpload("invalid_archive", f"archive member {name!r} lies inside "
                                                       f"{'/'.join(parts[:depth])!r}, which is a file",
                                    {"member": name})
        return self.root.joinpath(*parts)


def _unpack_zip(archive: Path, extractor: _Extractor) -> None:
    with zipfile.ZipFile(archive) as bundle:
        # A zip lists every member's size up front: an archive that says it is too large is refused before a
        # byte is written (one that lies is still stopped by the byte count while unpacking).
        declared = sum(info.file_size for info in bundle.infolist())
        if declared > extractor.max_bytes:
            raise extractor.too_large(f"declares {declared} unpacked bytes, more")
        for info in bundle.infolist():
            parts = extractor.parts(info.filename)
            mode = info.external_attr >> 16
            if stat.S_ISLNK(mode):
                raise InvalidUpload("unsafe_archive_member", f"archive member {info.filename!r} is a symbolic "
                                                             f"link; links are not accepted",
                                    {"member": info.filename})
            if parts is None:
                continue
            if info.flag_bits & 0x1:
                raise InvalidUpload("invalid_archive", f"archive member {info.filename!r} is encrypted",
                                    {"member": info.filename})
            if info.is_dir():
                extractor.directory(parts, info.filename)
                continue
            if stat.S_IFMT(mode) not in (0, stat.S_IFREG):  # 0: no Unix type recorded (DOS-made zips)
                raise InvalidUpload("unsafe_archive_member", f"archive member {info.filename!r} is not a regular "
                                                             f"file", {"member": info.filename})
            with bundle.open(info) as source:
                extractor.file(parts, info.filename, source)


def _unpack_tar(archive: Path, mode: str, extractor: _Extractor) -> None:
    with tarfile.open(archive, mode) as bundle:
        for member in bundle:  # streams: members are read in archive order, nothing is listed up front
            parts = extractor.parts(member.name)
            if member.issym() or member.islnk():
                kind = "symbolic" if member.issym() else "hard"
                raise InvalidUpload("unsafe_archive_member", f"archive member {member.name!r} is a {kind} link "
                                                             f"(to {member.linkname!r}); links are not accepted",
                                    {"member": member.name})
            if not (member.isreg() or member.isdir()):
                raise InvalidUpload("unsafe_archive_member", f"archive member {member.name!r} is a device, fifo "
                                                             f"or other special file", {"member": member.name})
            if parts is None:
                continue
            if member.isdir():
                extractor.directory(parts, member.name)
                continue
            source = bundle.extractfile(member)
            with source:
                extractor.file(parts, member.name, source)


# --- validating unpacked sequences -------------------------------------------------------------------------


@dataclass
class _Staged:
    """A validated sequence folder in staging, ready to be moved into a dataset."""

    name: str
    path: Path
    split: str
    scene: str | None


def find_sequences(root: Path, default_split: str) -> list[_Staged]:
    """Validate an unpacked upload and return its sequences; InvalidUpload naming the path on any problem.

    Accepted layouts: sequence folders (each with manifest.json) at the top or under one wrapping folder,
    a whole dataset folder (manifest.json with splits, possibly wrapped), or one sequence folder's contents.
    Sequences without a split in the upload get ``default_split``.
    """
    top = _unwrap(root)
    try:
        if not (top / MANIFEST).is_file():
            return _folder_sequences(top, root, default_split)
        manifest_format = _manifest_format(top / MANIFEST, root)
        if manifest_format == DATASET_FORMAT:
            return _dataset_sequences(top, root)
        if manifest_format == SEQUENCE_FORMAT:
            return [_validated_sequence(top, root, default_split, check_folder_name=False)]
        relative = _relative(top / MANIFEST, root)
        raise InvalidUpload("invalid_dataset", f"{relative}: field 'format' is {manifest_format!r}, expected "
                                               f"{SEQUENCE_FORMAT!r} or {DATASET_FORMAT!r}", {"path": relative})
    except (DatasetError, FrameError) as error:
        raise _invalid(error, root) from None


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


def _dataset_sequences(top: Path, root: Path) -> list[_Staged]:
    dataset = Dataset(top)
    listed = {checked_sequence_name(name) for name in dataset.names()}
    for entry in sorted(top.iterdir()):
        if entry.name != MANIFEST and entry.name not in listed:
            relative = _relative(entry, root)
            raise InvalidUpload("invalid_dataset", f"{relative} is not listed in "
                                                   f"{_relative(top / MANIFEST, root)}", {"path": relative})
    if not listed:
        raise InvalidUpload("invalid_dataset", f"{_relative(top / MANIFEST, root)} lists no sequences",
                            {"path": _relative(top / MANIFEST, root)})
    return [_validated_sequence(top / name, root, dataset.split_of(name)) for name in sorted(listed)]


def _folder_sequences(top: Path, root: Path, split: str) -> list[_Staged]:
    entries = sorted(top.iterdir())
    for entry in entries:
        relative = _relative(entry, root)
        if not entry.is_dir():
            raise InvalidUpload("invalid_dataset", f"{relative} is not inside a sequence folder (expected "
                                                   f"folders holding manifest.json and frame EXRs)",
                                {"path": relative})
        if not (entry / MANIFEST).is_file():
            raise InvalidUpload("missing_manifest", f"sequence folder {relative} has no {MANIFEST}",
                                {"path": relative})
    return [_validated_sequence(entry, root, split) for entry in entries]


def _validated_sequence(folder: Path, root: Path, split: str, check_folder_name: bool = True) -> _Staged:
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
        if entry.name not in listed:
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


# --- committing --------------------------------------------------------------------------------------------


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


def dataset_exists(storage: Storage, dataset_id: str) -> bool:
    return (storage.dataset(checked_dataset_id(dataset_id)) / MANIFEST).is_file()


def ingest_archive(storage: Storage, archive: Path, work: Path, dataset_id: str, *, create: bool,
                   split: str = "train", replace: bool = False, max_unpacked_bytes: int,
                   max_pixels: int | None = None, layout: Layout | None = None,
                   notes: UploadNotes | None = None) -> DatasetDetail:
    """Unpack and validate an uploaded archive in ``work`` (a staging workspace), then store it; ``max_pixels``:
    every EXR's header is checked against it before any frame is decoded, in any layout (FrameTooLargeUpload).

    ``create``: make dataset ``dataset_id`` (UploadConflict if it exists), else add the archive's sequences
    to it (UnknownDataset if it does not exist; UploadConflict for taken names unless ``replace``).
    ``layout`` (other than ``denoiser``): the archive holds a renderer's sequence folders, converted first
    (``service.upload_layouts``). Channels the format does not use are dropped either way; ``notes`` collects them
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
        check_unpacked_frame_pixels(unpacked, max_pixels, renderer_frames=renderer_frames)
    try:
        if renderer_frames:
            unpacked = import_renderer_folders(unpacked, _unwrap(unpacked), work / "imported", layout, split, notes)
        else:
            strip_unused_channels(unpacked, notes)
    except (DatasetError, FrameError) as error:
        raise _invalid(error, unpacked) from None
    sequences = find_sequences(unpacked, split)
    with dataset_lock(storage, dataset_id):
        if create:
            _create_dataset(storage, dataset_id, sequences, work)
        else:
            if not dataset_exists(storage, dataset_id):
                raise UnknownDataset("not_found", f"dataset {dataset_id!r} does not exist")
            _add_to_dataset(storage, dataset_id, sequences, work, replace)
    return describe_dataset(storage, dataset_id)


def check_unpacked_frame_pixels(root: Path, max_pixels: int, *, renderer_frames: bool = False) -> None:
    """FrameTooLargeUpload for the first EXR under ``root`` whose header declares more than ``max_pixels``.

    ``renderer_frames`` (an upload in another renderer's layout): files in a ``references/`` folder are reference
    renders, at up to 2x the frames' resolution (``model.exr.check_declared_pixels``)."""
    for path in sorted(root.rglob("*.exr")):
        if path.is_file():
            try:
                check_frame_file_pixels(path, max_pixels, _relative(path, root),
                                        reference_render=renderer_frames and path.parent.name == REFERENCES_FOLDER)
            except FrameTooLarge as error:
                raise _too_many_pixels(error) from None
            except FrameError:
                continue  # unreadable: the full validation names the problem


def _too_many_pixels(error: FrameTooLarge) -> FrameTooLargeUpload:
    return FrameTooLargeUpload("frame_too_large", str(error), {"path": error.source, "pixels": error.pixels,
                                                               "limit_pixels": error.limit})


# --- frame-by-frame uploads --------------------------------------------------------------------------------


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
                max_pixels: int | None = None) -> StagedSequence:
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
        read = read_layout_frame(upload, layout, mode="strict", max_pixels=max_pixels)
    except FrameTooLarge as error:
        raise _too_many_pixels(FrameTooLarge(label, error.problem, error.pixels, error.limit)) from None
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


# --- reading and deleting ----------------------------------------------------------------------------------


def _open(storage: Storage, dataset_id: str) -> Dataset:
    root = storage.dataset(checked_dataset_id(dataset_id))
    if not (root / MANIFEST).is_file():
        raise UnknownDataset("not_found", f"dataset {dataset_id!r} does not exist")
    return Dataset(root)


def sequence_buffers(sequence: Sequence) -> list[str]:
    """Buffers of the sequence's first frame, from the EXR headers only (no pixels decoded)."""
    present: set[str] = set()
    for part in OpenEXR.File(str(sequence.frame_path(0)), header_only=True).parts:
        for channel in part.header["channels"]:
            slot = CHANNEL_SLOTS.get(channel.name)
            if slot is not None:
                present.add(slot[0])
    return [name for name in BUFFERS if name in present]


def describe_dataset(storage: Storage, dataset_id: str) -> DatasetDetail:
    dataset = _open(storage, dataset_id)
    sequences = []
    for sequence in dataset.sequences():
        sequences.append(SequenceInfo(
            name=sequence.path.name, split=dataset.split_of(sequence.path.name), scene=sequence.scene,
            frames=len(sequence), width=sequence.width, height=sequence.height, scales=list(sequence.scales),
            buffers=sequence_buffers(sequence), camera_cuts=sequence.cuts,
        ))
    splits = {split: SplitSummary(**summary) for split, summary in dataset.summary().items()}
    return DatasetDetail(
        id=dataset_id,
        frames=sum(s.frames for s in sequences),
        scenes=sorted({s.scene for s in sequences if s.scene is not None}),
        splits=splits,
        sequences=sequences,
    )


def list_datasets(storage: Storage) -> list[DatasetSummary]:
    """Every stored dataset, by id; reads manifests only."""
    if not storage.datasets.is_dir():
        return []
    summaries = []
    for root in sorted(storage.datasets.iterdir()):
        try:
            dataset = Dataset(root)
            sequences = dataset.sequences()
        except (DatasetError, OSError) as error:  # deleted meanwhile, or damaged on disk: list the others
            log.warning("skipping dataset folder %s: %s", root, error)
            continue
        summaries.append(DatasetSummary(
            id=root.name,
            sequences=len(sequences),
            frames=sum(len(s) for s in sequences),
            scenes=sorted({s.scene for s in sequences if s.scene is not None}),
            splits={split: len(dataset.names(split)) for split in SPLITS},
        ))
    return summaries


def delete_dataset(storage: Storage, dataset_id: str) -> None:
    _open(storage, dataset_id)  # 404 before a lock file is made for an unknown id
    with dataset_lock(storage, checked_dataset_id(dataset_id)):
        _open(storage, dataset_id)
        storage.remove_tree(storage.dataset(dataset_id))
