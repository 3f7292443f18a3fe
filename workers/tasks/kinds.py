"""The job kinds: which module checks and runs each one.

Every kind module has ``check(params, storage[, settings]) -> dict`` (run by the API before queueing: ApiError
for anything wrong, else the parameters with defaults filled in, as stored in the job record) and
``run(context) -> dict`` (run by the worker: the job's result).
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

from pydantic import BaseModel

from service.settings import Settings
from service.storage import Storage

KIND_MODULES = {
    "generate": "workers.tasks.generate",
    "train": "workers.tasks.train",
    "evaluate": "workers.tasks.evaluate",
    "benchmark": "workers.tasks.evaluate",
    "infer": "workers.tasks.infer",
    "fit": "workers.tasks.fit",
}


def module_for(kind: str) -> ModuleType:
    if kind not in KIND_MODULES:
        raise ValueError(f"unknown job kind {kind!r}; kinds: {', '.join(KIND_MODULES)}")
    return importlib.import_module(KIND_MODULES[kind])


def check(kind: str, params: BaseModel, storage: Storage, settings: Settings) -> dict[str, Any]:
    module = module_for(kind)
    if kind in ("train", "fit"):
        return module.check(params, storage, settings)
    return module.check(params, storage)
