"""The job kinds the worker runs: which module's ``run(context) -> dict`` (the job's result) runs each one.

Their checks, run by the API before queueing, are in ``core.jobs`` (``core.jobs.kinds.check``).
"""

from __future__ import annotations

import importlib
from types import ModuleType

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
