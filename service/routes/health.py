"""/health (liveness) and /ready (readiness: Redis, MLflow and Celery workers). Neither needs the API key.

/ready answers 503 with the same body when anything is down, so a load balancer or docker-compose health
check can use the status code alone while a person reads which dependency failed and why. Every probe has a
short timeout: a readiness check that hangs is worse than one that says "down".
"""

from __future__ import annotations

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

from service.schemas import DependencyCheck, Health, Readiness
from service.settings import Settings, get_settings

router = APIRouter(tags=["health"])

REDIS_TIMEOUT_SECONDS = 1.0
MLFLOW_TIMEOUT_SECONDS = 2.0
WORKER_PING_SECONDS = 1.0


def redacted(url: str) -> str:
    """The URL without its password, fit for a response body."""
    parts = urlsplit(url)
    if parts.password is None:
        return url
    netloc = f"{parts.username or ''}:***@{parts.hostname}" + (f":{parts.port}" if parts.port else "")
    return urlunsplit(parts._replace(netloc=netloc))


def check_redis(settings: Settings) -> DependencyCheck:
    url = redacted(settings.redis_url)
    client = redis.Redis.from_url(settings.redis_url, socket_connect_timeout=REDIS_TIMEOUT_SECONDS,
                                  socket_timeout=REDIS_TIMEOUT_SECONDS)
    try:
        start = time.perf_counter()
        client.ping()
        return DependencyCheck(status="ok", detail=f"PING {url} answered in "
                                                   f"{(time.perf_counter() - start) * 1000:.1f} ms")
    except (redis.RedisError, OSError) as error:
        return DependencyCheck(status="down", detail=f"{url}: {error}")
    finally:
        client.close()


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
            return DependencyCheck(status="down", detail=f"GET {redacted(url)}: {type(error).__name__}: {error}")
        if answer.status_code != 200:
            return DependencyCheck(status="down", detail=f"GET {redacted(url)} answered {answer.status_code}")
        return DependencyCheck(status="ok", detail=f"GET {redacted(url)} answered 200")
    if scheme in ("", "file"):
        return _writable_folder(Path(urlsplit(uri).path if scheme else uri), "file store folder")
    return DependencyCheck(status="skipped", detail=f"tracking URI scheme {scheme!r} is not checked from here")


def _writable_folder(folder: Path, what: str) -> DependencyCheck:
    if not folder.is_dir():
        return DependencyCheck(status="down", detail=f"{what} {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        return DependencyCheck(status="down", detail=f"{what} {folder} is not writable")
    return DependencyCheck(status="ok", detail=f"{what} {folder} is writable")


def ping_workers() -> list[str]:
    """Host names of the Celery workers answering a broadcast ping within WORKER_PING_SECONDS."""
    from workers.celery_app import app  # imported here: celery is only needed once /ready is asked

    replies = app.control.ping(timeout=WORKER_PING_SECONDS) or []
    return sorted(name for reply in replies for name in reply)


@dataclass(frozen=True)
class Probes:
    """The checks /ready runs; a dependency so tests can replace any of them."""

    redis: Callable[[Settings], DependencyCheck] = check_redis
    mlflow: Callable[[Settings], DependencyCheck] = check_mlflow
    workers: Callable[[], list[str]] = ping_workers


def get_probes() -> Probes:
    return Probes()


@router.get("/health", response_model=Health, summary="Liveness")
def health() -> Health:
    """Always ok while the process serves HTTP; dependencies are checked by /ready."""
    return Health()


@router.get(
    "/ready",
    response_model=Readiness,
    summary="Readiness: Redis, MLflow and Celery workers",
    responses={503: {"model": Readiness, "description": "something is down; `down` names it"}},
)
def ready(settings: Annotated[Settings, Depends(get_settings)],
          probes: Annotated[Probes, Depends(get_probes)]) -> JSONResponse:
    redis_check = probes.redis(settings)
    mlflow_check = probes.mlflow(settings)
    workers: list[str] = []
    if redis_check.status != "ok":
        # The worker ping goes through the broker; with Redis down it could only hang or fail.
        workers_detail = "not checked: Redis (the Celery broker) is down"
    else:
        try:
            workers = probes.workers()
            workers_detail = (f"{len(workers)} Celery worker{'s' if len(workers) != 1 else ''} answered ping"
                              if workers else f"no Celery worker answered ping within {WORKER_PING_SECONDS:g} s")
        except Exception as error:  # any broker failure means the same thing here: no worker reachable
            workers_detail = f"worker ping failed: {type(error).__name__}: {error}"
    down = [name for name, check in (("redis", redis_check), ("mlflow", mlflow_check)) if check.status == "down"]
    if not workers:
        down.append("workers")
    body = Readiness(status="unavailable" if down else "ready", redis=redis_check, mlflow=mlflow_check,
                     workers=workers, workers_detail=workers_detail, down=down)
    return JSONResponse(body.model_dump(), status_code=503 if down else 200)
