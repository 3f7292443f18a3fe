"""Upload errors: each is a caller's mistake, with one HTTP status in ``service.http.errors.ERROR_STATUS``."""

from __future__ import annotations

from typing import Any


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


def _too_large(what: str, size: int, limit: int, at_least: bool = False) -> UploadTooLarge:
    amount = f"at least {size}" if at_least else str(size)
    return UploadTooLarge("payload_too_large", f"the {what} is {amount} bytes; the limit is {limit} bytes",
                          {"limit_bytes": limit})
