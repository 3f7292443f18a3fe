"""Bodies of /jobs: the POST body per kind, the job record, logs and results."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Field, create_model

from core.jobs.kinds import KINDS, Kind
from core.jobs.specs import JobDevice, JobKind, JobState, TrainParams


def _job_create(kind: Kind) -> type[BaseModel]:
    """The POST /jobs body of one kind: ``{"kind": KIND, "params": PARAMS, "device": ...}`` as a model named
    ``<Kind>JobCreate`` (its OpenAPI schema name), with an example built from the parameters' first example."""
    params = kind.params.model_config["json_schema_extra"]["examples"][0]
    example = {"kind": kind.name, "params": params, "device": kind.example_device}
    return create_model(
        f"{kind.name.capitalize()}JobCreate",
        __config__=ConfigDict(extra="forbid", strict=True, json_schema_extra={"examples": [example]}),
        __module__=__name__,
        kind=(Literal[kind.name], ...),
        params=(kind.params, ...),
        device=(Literal[kind.devices], Field("cpu", description="cpu: queue 'cpu'; gpu: queue 'gpu' (the job runs "
                                                                "on CUDA)")),
    )


# One body per kind of the table (core.jobs.kinds.KINDS), named <Kind>JobCreate.
JOB_CREATE = {name: _job_create(kind) for name, kind in KINDS.items()}

# POST /jobs body: the kind picks the parameter schema.
JobCreate = Annotated[Union[tuple(JOB_CREATE.values())], Field(discriminator="kind")]


class JobProgress(BaseModel):
    """Progress of the running execution (the same shape Celery's update_state carries)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"current": 120, "total": 2000, "message": "step 120/2000, loss 0.4210", "eta_seconds": 310.5}]})

    current: int = Field(description="units done (steps, frames, method-sequence runs)")
    total: int = Field(description="units in all; 0 until known")
    message: str
    eta_seconds: float | None = Field(description="estimated seconds left, from this execution's rate so far")


class JobErrorInfo(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"code": "invalid_input", "message": "ValueError: sequence 'a' is 8x8, smaller than the 64x64 crop"}]})

    code: str
    message: str


class Job(BaseModel):
    """A job: what was asked, where it runs, how far it got, and what came out."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "id": "5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e", "kind": "train", "state": "running",
        "params": {**TrainParams.model_config["json_schema_extra"]["examples"][0]},
        "device": "gpu", "queue": "gpu", "created_at": "2026-11-22T06:30:57.715000Z",
        "started_at": "2026-11-22T06:31:02.100000Z", "finished_at": None,
        "progress": {"current": 120, "total": 2000, "message": "step 120/2000, loss 0.4210", "eta_seconds": 310.5},
        "mlflow_run_id": "9a8b7c6d5e4f", "mlflow_url": "http://mlflow.local:5000/#/experiments/1/runs/9a8b7c6d5e4f",
        "result": None, "error": None, "attempts": 1, "cancel_requested": False}]})

    id: str
    kind: JobKind
    state: JobState
    params: dict[str, Any] = Field(description="the parameters with every default filled in")
    device: JobDevice
    queue: str = Field(description="Celery queue the job was sent to")
    created_at: datetime
    started_at: datetime | None = Field(description="first start of an execution")
    finished_at: datetime | None
    progress: JobProgress
    mlflow_run_id: str | None
    mlflow_url: str | None = Field(description="the run in the MLflow UI (when the server knows the UI's URL)")
    result: dict[str, Any] | None = Field(description="kind-specific summary once the job succeeded")
    error: JobErrorInfo | None
    attempts: int = Field(description="executions started (more than 1 after a worker was lost and the job resumed)")
    cancel_requested: bool = Field(description="a cancel was asked; a running job stops at its next progress point")


class JobLogs(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"lines": [
        "2026-11-22 06:31:02,100 INFO denoiser.jobs.5f0c3a9e: attempt 1 of train job started on worker-1",
        "2026-11-22 06:31:12,301 INFO denoiser.jobs.5f0c3a9e: progress 40/2000, ETA 490 s: step 40/2000"]}]})

    lines: list[str] = Field(description="the last lines of the job's log, oldest first")


class ResultFrame(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"frame": "frame_0003.exr", "frame_index": 3, "bytes": 196_830,
         "url": "/jobs/5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e/results/kitchen_0/frame_0003.exr"}]})

    frame: str = Field(description="file name")
    frame_index: int
    bytes: int
    url: str


class ResultSequence(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"name": "kitchen_0", "frames": [
        ResultFrame.model_config["json_schema_extra"]["examples"][0]]}]})

    name: str
    frames: list[ResultFrame]


class JobResults(BaseModel):
    """Output frames of an infer job: one-part float32 R,G,B EXRs at the model's output resolution."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "job_id": "5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e", "state": "succeeded", "complete": True,
        "zip_url": "/jobs/5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e/results.zip",
        "sequences": [ResultSequence.model_config["json_schema_extra"]["examples"][0]]}]})

    job_id: str
    state: JobState
    complete: bool = Field(description="the job succeeded: every frame is there")
    zip_url: str
    sequences: list[ResultSequence]
