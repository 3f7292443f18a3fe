"""The module whose ``run(context) -> dict`` (the job's result) runs each job kind, as ``core.jobs.kinds.KINDS``
names it (the table of kinds: parameters, checks, run modules)."""

from __future__ import annotations

import importlib
from types import ModuleType

from core.jobs.kinds import KINDS, kind_of

KIND_MODULES = {name: kind.run for name, kind in KINDS.items()}


def module_for(kind: str) -> ModuleType:
    return importlib.import_module(kind_of(kind).run)
