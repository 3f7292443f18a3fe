"""The REST API's answers as typed objects: Session, Job, Dataset, Model, ModelVersion, and FrameResult.

Each has the fields of its REST answer (docs/service.md) as attributes, nested ones typed (``session.model.buffers``,
``job.progress.current``, ``job.error.message``); a field an older server leaves out is None, one a newer server
adds is kept in ``to_dict()``. They still read as the dicts the client used to return, ``job["state"]``,
``session.get("token")``, ``"id" in dataset``, with the JSON values as sent, so code written against dicts keeps
working; ``to_dict()`` gives the answer as sent (the CLI prints it).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, NamedTuple


@dataclass(kw_only=True, eq=False)
class Answer:
    """A JSON object the server answered, with its known fields as attributes (see the module notes)."""

    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)
    NESTED = {}  # field name -> the Answer class its JSON object becomes

    @classmethod
    def from_dict(cls, body: dict[str, Any] | None):
        if body is None or isinstance(body, cls):
            return body
        if not isinstance(body, dict):
            raise TypeError(f"{cls.__name__}: expected a JSON object, got {type(body).__name__}")
        values = {}
        for item in dataclasses.fields(cls):
            if item.name == "raw":
                continue
            value = body.get(item.name)
            nested = cls.NESTED.get(item.name)
            values[item.name] = nested.from_dict(value) if nested and isinstance(value, dict) else value
        return cls(raw=dict(body), **values)

    def to_dict(self) -> dict[str, Any]:
        return dict(self.raw)

    def __eq__(self, other: object) -> bool:  # equal to another answer or a dict with the same JSON
        if isinstance(other, Answer):
            return type(other) is type(self) and other.raw == self.raw
        return self.raw == other if isinstance(other, dict) else NotImplemented

    __hash__ = None  # mutable, as the dict it stands for

    def __getitem__(self, key: str) -> Any:
        return self.raw[key]

    def get(self, key: str, default: Any = None) -> Any:
        return self.raw.get(key, default)

    def __contains__(self, key: object) -> bool:
        return key in self.raw

    def keys(self):
        return self.raw.keys()

    def items(self):
        return self.raw.items()


@dataclass(kw_only=True, eq=False)
class SessionModel(Answer):
    name: str | None = None
    version: str | None = None
    alias: str | None = None
    method: str | None = None
    preset: str | None = None
    scale: int | None = None
    params: int | None = None
    source: str | None = None
    buffers: list[str] | None = None


@dataclass(kw_only=True, eq=False)
class SessionMirror(Answer):
    current: bool | None = None
    last_written_frame: int | None = None
    pending_since: str | None = None


@dataclass(kw_only=True, eq=False)
class Session(Answer):
    NESTED = {"model": SessionModel, "mirror": SessionMirror}
    id: str | None = None
    model: SessionModel | None = None
    created_at: str | None = None
    last_used_at: str | None = None
    expires_at: str | None = None
    frames_processed: int | None = None
    next_frame_index: int | None = None
    on_gap: str | None = None
    resolution: list[int] | None = None
    choice: dict | None = None
    layout: str | dict | None = None
    token: str | None = None
    mirror: SessionMirror | None = None  # whether Redis holds the session as it is (a restart continues it)


@dataclass(kw_only=True, eq=False)
class JobProgress(Answer):
    current: int | None = None
    total: int | None = None
    message: str | None = None
    eta_seconds: float | None = None


@dataclass(kw_only=True, eq=False)
class JobError(Answer):
    code: str | None = None
    message: str | None = None


@dataclass(kw_only=True, eq=False)
class Job(Answer):
    NESTED = {"progress": JobProgress, "error": JobError}
    id: str | None = None
    kind: str | None = None
    state: str | None = None
    params: dict | None = None
    device: str | None = None
    queue: str | None = None
    created_at: str | None = None
    started_at: str | None = None
    finished_at: str | None = None
    progress: JobProgress | None = None
    mlflow_run_id: str | None = None
    mlflow_url: str | None = None
    result: dict | None = None
    error: JobError | None = None
    attempts: int | None = None
    cancel_requested: bool | None = None


@dataclass(kw_only=True, eq=False)
class Dataset(Answer):
    id: str | None = None
    sequences: Any = None  # a count in GET /datasets, the sequences in GET /datasets/{id}
    frames: int | None = None
    scenes: list[str] | None = None
    splits: dict | None = None


@dataclass(kw_only=True, eq=False)
class ModelVersion(Answer):
    name: str | None = None
    version: str | None = None
    run_id: str | None = None
    created_at: str | None = None
    method: str | None = None
    preset: str | None = None
    scale: int | None = None
    params: int | None = None
    flops_per_pixel: float | None = None
    metrics: dict | None = None
    tags: dict | None = None
    aliases: list[str] | None = None
    ref: str | None = None


@dataclass(kw_only=True, eq=False)
class Model(Answer):
    name: str | None = None
    description: str | None = None
    latest_version: str | None = None
    aliases: dict | None = None
    versions: list[ModelVersion] | None = None

    @classmethod
    def from_dict(cls, body):
        model = super().from_dict(body)
        if model is not None and isinstance(model.versions, list):
            model.versions = [ModelVersion.from_dict(v) if isinstance(v, dict) else v for v in model.versions]
        return model


class FrameResult(NamedTuple):
    """One denoised frame: ``image`` (H*s, W*s, 3) float32 linear RGB and ``info`` (a FrameInfo). A tuple, so
    ``image, info = client.send_frame(...)`` reads as it always did."""

    image: Any
    info: Any
