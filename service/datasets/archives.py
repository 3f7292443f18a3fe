"""Archive safety: zip, tar and tar.gz members are extracted by hand, never with ``extractall``.

Absolute paths, ``..``, links and device files are refused with an error naming the member, and the unpacked
size is bounded (against zip bombs).
"""

from __future__ import annotations

import re
import stat
import tarfile
import zipfile
import zlib
from pathlib import Path
from typing import BinaryIO, Literal

from service.datasets.errors import InvalidUpload, UploadTooLarge


ArchiveKind = Literal["zip", "tar", "tar.gz"]


CHUNK_BYTES = 1024 * 1024


MAX_ARCHIVE_MEMBERS = 100_000


# Files that archivers on macOS add; they are dropped rather than refused.
_IGNORED_FOLDERS = {"__MACOSX"}


_IGNORED_FILES = {".DS_Store", "Thumbs.db"}


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
