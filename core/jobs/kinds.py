"""Each job kind's check, run by the API before queueing (the worker runs kinds: ``workers.tasks.kinds``).

Every module here has ``check(params, storage[, settings]) -> dict``: a domain error (``core.errors``) for
anything wrong, else the parameters with defaults filled in, as stored in the job record.
"""

from __future__ import annotations

import importlib
from typing import Any

from pydantic import BaseModel

from core.settings import Settings
from core.storage import Storage

CHECK_MODULES = {
    "generate": "core.jobs.generate",
    "train": "core.jobs.train",
    "evaluate": "core.jobs.evaluate",
    "benchmark": "core.jobs.evaluate",
    "infer": "core.jobs.infer",
    "fit": "core.jobs.fit",
}


def check(kind: str, params: BaseModel, storage: Storage, settings: Settings) -> dict[str, Any]:
    if kind not in CHECK_MODULES:
        raise ValueError(f"unknown job kind {kind!r}; kinds: {', '.join(CHECK_MODULES)}")
    module = importlib.import_module(CHECK_MODULES[kind])
    if kind in ("train", "fit"):
        return module.check(params, storage, settings)
    return module.check(params, storage)
