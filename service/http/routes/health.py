"""/health (liveness) and /ready (readiness: Redis, storage, MLflow; workers' heartbeats listed). Neither needs
the API key.

/ready answers 503 with the same body when anything this API needs is down, so a load balancer or docker-compose
health check can use the status code alone while a person reads which dependency failed. The body is public: it
names no path, URL or host of a dependency (those go to the API's log). Every probe has a short timeout: a
readiness check that hangs is worse than one that says "down".
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated
from urllib.parse import urlsplit, urlunsplit

import httpx
import redis
from fastapi import APIRouter, Depends
from fastapi.responses import JSONResponse

from core.heartbeats import TTL_INTERVALS, WorkerBeat, read_beats
from core.redis_persistence import Persistence, persistence_of_url, persistence_warning
from service.http.schemas.health import DependencyCheck, Health, Readiness
from core.settings import Settings, get_settings

router = APIRouter(tags=["health"])

REDIS_TIMEOUT_SECONDS = 1.0
MLFLOW_TIMEOUT_SECONDS = 2.0

log = logging.getLogger("denoiser.api")


def redacted(url: str) -> str:
    """The URL without its password, fit for a response body."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    netloc = f"{parts.username or ''}:***@{parts.hostname}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def check_redis(settings: Settings) -> DependencyCheck:
    client = redis.Redis.from_url(settings.redis_url, socket_connect_timeout=REDIS_TIMEOUT_SECONDS,
                                  socket_timeout=REDIS_TIMEOUT_SECONDS)
    try:
        start = time.perf_counter()
        client.ping()
        return DependencyCheck(status="ok", detail=f"PING answered in {(time.perf_counter() - start) * 1000:.1f} ms")
    except (redis.RedisError, OSError) as error:
        log.warning("/ready: Redis at %s: %s", redacted(settings.redis_url), error)
        return DependencyCheck(status="down", detail=f"PING failed ({type(error).__name__}; see the API log)")
    finally:
        client.close()


def check_storage(settings: Settings) -> DependencyCheck:
    """The data folder (datasets, staging, job files) exists and is writable."""
    return _writable_folder(Path(settings.data_dir), "data folder")


def check_mlflow(settings: Settings) -> DependencyCheck:
    """sqlite: the database file's folder is writable; http(s): GET <uri>/health; file stores: folder writable."""
    uri = settings.resolved_tracking_uri()
    scheme = urlsplit(uri).scheme
    if scheme == "sqlite":
        location = uri.removeprefix("sqlite://").removeprefix("/")  # sqlite:///rel or sqlite:////abs
        if location in ("", ":memory:"):
            return DependencyCheck(status="ok", detail="in-memory sqlite store")
        return _writable_folder(Path(location).parent, "sqlite store folder")
    if scheme in ("http", "https"):
        url = uri.rstrip("/") + "/health"
        try:
            answer = httpx.get(url, timeout=MLFLOW_TIMEOUT_SECONDS)
        except httpx.HTTPError as error:
            log.warning("/ready: GET %s: %s", redacted(url), error)
            return DependencyCheck(status="down", detail=f"GET /health failed ({type(error).__name__}; see the "
                                                         f"API log)")
        if answer.status_code != 200:
            return DependencyCheck(status="down", detail=f"GET /health answered {answer.status_code}")
        return DependencyCheck(status="ok", detail="GET /health answered 200")
    if scheme in ("", "file"):
        return _writable_folder(Path(urlsplit(uri).path if scheme else uri), "file store folder")
    return DependencyCheck(status="skipped", detail=f"tracking URI scheme {scheme!r} is not checked from here")


def _writable_folder(folder: Path, what: str) -> DependencyCheck:
    """Whether ``folder`` can be written; the answer names the folder's role, the log its path."""
    if not folder.is_dir():
        log.warning("/ready: %s %s does not exist", what, folder)
        return DependencyCheck(status="down", detail=f"{what} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        log.warning("/ready: %s %s is not writable", what, folder)
        return DependencyCheck(status="down", detail=f"{what} is not writable")
    return DependencyCheck(status="ok", detail=f"{what} is writable")


def redis_persistence(settings: Settings) -> Persistence:
    """aof, rdb, none or unknown (core.redis_persistence)."""
    return persistence_of_url(settings.redis_url)


def worker_beats(settings: Settings) -> list[WorkerBeat]:
    """The workers whose heartbeat (core.heartbeats) is alive in Redis."""
    client = redis.Redis.from_url(settings.redis_url, socket_connect_timeout=REDIS_TIMEOUT_SECONDS,
                                  socket_timeout=REDIS_TIMEOUT_SECONDS)
    try:
        return read_beats(client)
    finally:
        client.close()


@dataclass(frozen=True)
class Probes:
    """The checks /ready runs; a dependency so tests can replace any of them."""

    redis: Callable[[Settings], DependencyCheck] = check_redis
    mlflow: Callable[[Settings], DependencyCheck] = check_mlflow
    storage: Callable[[Settings], DependencyCheck] = check_storage
    workers: Callable[[Settings], list[WorkerBeat]] = worker_beats
    persistence: Callable[[Settings], Persistence] = redis_persistence


def get_probes() -> Probes:
    return Probes()


@router.get("/health", response_model=Health, summary="Liveness")
def health() -> Health:
    """Always ok while the process serves HTTP; dependencies are checked by /ready."""
    return Health()


@router.get(
    "/ready",
    response_model=Readiness,
    summary="Readiness: this API can serve (Redis, storage, MLflow); workers reported beside",
    responses={503: {"model": Readiness, "description": "something this API needs is down; `down` names it"}},
)
def ready(settings: Annotated[Settings, Depends(get_settings)],
          probes: Annotated[Probes, Depends(get_probes)]) -> JSONResponse:
    """200 when Redis, the data folder and MLflow answer. Workers do not decide it (a worker busy training is
    not an API that cannot serve, and jobs wait in the queue for one): their heartbeats are listed, and
    `workers_detail` says how many are alive and what they run. `redis_persistence` says whether Redis keeps
    its data across its own restart; `none` adds a line to `warnings` but the API stays ready."""
    checks = {"redis": probes.redis(settings), "storage": probes.storage(settings),
              "mlflow": probes.mlflow(settings)}
    workers: list[str] = []
    # Without persistence a Redis restart loses the queue and the sessions: said, yet still ready (it serves).
    persistence: Persistence = probes.persistence(settings) if checks["redis"].status == "ok" else "unknown"
    warning = persistence_warning(persistence) if checks["redis"].status == "ok" else None
    if checks["redis"].status != "ok":
        workers_detail = "not checked: Redis (where workers write their heartbeats) is down"
    else:
        try:
            beats = probes.workers(settings)
            workers = [beat.hostname for beat in beats]
            workers_detail = _describe_workers(beats, settings.worker_heartbeat_seconds)
        except (redis.RedisError, OSError) as error:
            log.warning("/ready: reading worker heartbeats: %s", error)
            workers_detail = f"worker heartbeats could not be read ({type(error).__name__})"
    down = [name for name, check in checks.items() if check.status == "down"]
    body = Readiness(status="unavailable" if down else "ready", redis=checks["redis"], storage=checks["storage"],
                     mlflow=checks["mlflow"], workers=workers, workers_detail=workers_detail, down=down,
                     redis_persistence=persistence, warnings=[warning] if warning else [])
    return JSONResponse(body.model_dump(), status_code=503 if down else 200)


def _describe_workers(beats: list[WorkerBeat], interval: float) -> str:
    if not beats:
        return (f"no worker heartbeat in the last {TTL_INTERVALS * interval:g} s: jobs wait in the queue until a "
                f"worker starts")
    running = [f"{beat.hostname} runs job {beat.job}" for beat in beats if beat.job]
    window = TTL_INTERVALS * interval
    alive = f"{len(beats)} worker{'s' if len(beats) != 1 else ''} alive (heartbeat within {window:g} s)"
    return alive + (f"; {', '.join(running)}" if running else "; all idle")
