"""The one table of job kinds: each kind's parameters, its check, the worker module that runs it, its queues.

Everything else about the kinds is derived from ``KINDS``: ``core.names.JOB_KINDS`` (plain names for the client;
a test holds them equal), ``JOB_PARAMS``, the REST bodies (``service.http.schemas.jobs``), the worker's dispatch
(``workers.tasks.kinds``) and the CLI's options (``cli.options.add_model_options`` over each kind's parameters).

A check module has ``check(params, storage, settings) -> dict``, run by the API before queueing: a domain error
(``core.errors``) for anything wrong, else the parameters with defaults filled in, as stored in the job record.
A run module has ``run(context) -> dict`` (the job's result); it is named, not imported, so core never imports
the workers.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel

from core.jobs.specs import (
    BenchmarkParams,
    EvaluateParams,
    FitParams,
    GenerateParams,
    InferParams,
    StabilityParams,
    TrainParams,
)
from core.names import DEVICES, QUEUE_FOR_DEVICE
from core.settings import Settings
from core.storage import Storage


@dataclass(frozen=True)
class Kind:
    name: str
    params: type[BaseModel]
    check: str  # module with check(params, storage, settings)
    run: str  # worker module with run(context)
    devices: tuple[str, ...] = DEVICES  # the devices a job may ask for; a job on device D goes to queue D
    example_device: str = "cpu"  # the device of the REST body's example

    def queue(self, device: str) -> str:
        if device not in self.devices:
            raise ValueError(f"{self.name} jobs run on {', '.join(self.devices)}, not {device!r}")
        return QUEUE_FOR_DEVICE[device]


KINDS: dict[str, Kind] = {kind.name: kind for kind in (
    Kind("generate", GenerateParams, "core.jobs.generate", "workers.tasks.generate"),
    Kind("train", TrainParams, "core.jobs.train", "workers.tasks.train", example_device="gpu"),
    Kind("evaluate", EvaluateParams, "core.jobs.evaluate", "workers.tasks.evaluate"),
    Kind("benchmark", BenchmarkParams, "core.jobs.evaluate", "workers.tasks.evaluate"),
    Kind("infer", InferParams, "core.jobs.infer", "workers.tasks.infer"),
    Kind("fit", FitParams, "core.jobs.fit", "workers.tasks.fit"),
    Kind("stability", StabilityParams, "core.jobs.stability", "workers.tasks.stability"),
)}

JOB_PARAMS: dict[str, type[BaseModel]] = {name: kind.params for name, kind in KINDS.items()}


def kind_of(name: str) -> Kind:
    if name not in KINDS:
        raise ValueError(f"unknown job kind {name!r}; kinds: {', '.join(KINDS)}")
    return KINDS[name]


def check(kind: str, params: BaseModel, storage: Storage, settings: Settings) -> dict[str, Any]:
    return importlib.import_module(kind_of(kind).check).check(params, storage, settings)
