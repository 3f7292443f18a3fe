"""Receiving an upload: a request body streamed to a staging file, bounded in size."""

from __future__ import annotations

from collections.abc import AsyncIterable
from pathlib import Path

from service.datasets.errors import InvalidUpload, _too_large


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
