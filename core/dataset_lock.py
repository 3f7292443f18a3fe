"""The dataset lock and staging workspaces, taken by uploads (API) and by generate jobs (workers).

Changes to one dataset are serialized by a lock file (``staging/locks/<id>.lock``, ``flock``), which works
across threads and across processes sharing the data folder.
"""

from __future__ import annotations

import fcntl
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from core.storage import Storage, checked_id


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
