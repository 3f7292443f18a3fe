"""Bodies of GET /health and GET /ready."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from core.redis_persistence import Persistence


CheckStatus = Literal["ok", "down", "skipped"]


class Health(BaseModel):
    """Liveness: the process answers HTTP. Says nothing about Redis, MLflow or workers (see /ready)."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"status": "ok"}]})

    status: Literal["ok"] = "ok"


class DependencyCheck(BaseModel):
    """One dependency's state; ``detail`` says what was tried and, when down, what failed."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"status": "ok", "detail": "PING answered in 0.4 ms"}]
    })

    status: CheckStatus = Field(description="ok, down, or skipped (not checkable from here)")
    detail: str = Field(description="what was checked and, when down, why")


class Readiness(BaseModel):
    """Whether this API can serve; answered with 200 when ``down`` is empty, else 503 with this body. Workers are
    listed from their heartbeats but do not decide it."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [
            {
                "status": "ready",
                "redis": {"status": "ok", "detail": "PING answered in 0.4 ms"},
                "storage": {"status": "ok", "detail": "data folder is writable"},
                "mlflow": {"status": "ok", "detail": "GET /health answered 200"},
                "workers": ["celery@gpu-box", "celery@cpu-box"],
                "workers_detail": "2 workers alive (heartbeat within 30 s); celery@gpu-box runs job 7f3c...",
                "down": [],
                "redis_persistence": "aof",
                "warnings": [],
            },
            {
                "status": "unavailable",
                "redis": {"status": "down", "detail": "PING failed (ConnectionError; see the API log)"},
                "storage": {"status": "ok", "detail": "data folder is writable"},
                "mlflow": {"status": "ok", "detail": "sqlite store folder is writable"},
                "workers": [],
                "workers_detail": "not checked: Redis (where workers write their heartbeats) is down",
                "down": ["redis"],
                "redis_persistence": "unknown",
                "warnings": [],
            },
        ]
    })

    status: Literal["ready", "unavailable"]
    redis: DependencyCheck
    storage: DependencyCheck
    mlflow: DependencyCheck
    workers: list[str] = Field(description="host names of the workers whose heartbeat is alive")
    workers_detail: str = Field(description="how many workers are alive and which jobs they run, or why unknown")
    down: list[str] = Field(description="the dependencies that are down: any of redis, storage, mlflow")
    redis_persistence: Persistence = Field(
        description="how Redis keeps its data across its own restart: aof (append-only file), rdb (snapshots "
                    "only), none (a Redis restart empties the job queue and the sessions), unknown (Redis down, "
                    "or CONFIG refused)")
    warnings: list[str] = Field(default_factory=list, description="what does not make the API unready but an "
                                                                  "operator should know (Redis without persistence)")
