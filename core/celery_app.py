"""The one Celery app, shared by the API (which sends jobs) and the workers (which run them).

Start a worker with `denoiser worker` (or `celery -A core.celery_app worker -P solo -Q cpu`). The solo pool runs
tasks in the worker's main process, which is not daemonic, so a training task can start DDP ranks (prefork
children are daemonic and cannot have children of their own).

The task modules are named in ``include``, which only a starting worker imports: the API sends jobs by task name
(``core.jobs.dispatch``) and never loads them. This is the only core module that imports Celery.
"""

from __future__ import annotations

from typing import Any

from celery import Celery
from kombu import Queue

from core.names import QUEUES
from core.settings import Settings, get_settings

TASK_MODULES = ("workers.tasks.jobs", "workers.tasks.nodes")


def celery_config(settings: Settings) -> dict[str, Any]:
    """Every Celery setting of the app (queues aside: ``core.names.QUEUES``)."""
    # Longer than any job: Redis re-delivers an unacknowledged message only after this many seconds.
    visibility_timeout = settings.job_time_limit_seconds + 3600
    return dict(
        task_default_queue="cpu",
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_track_started=True,
        worker_prefetch_multiplier=1,
        worker_hijack_root_logger=False,
        broker_connection_retry_on_startup=True,
        broker_transport_options={"visibility_timeout": visibility_timeout},
        result_backend_transport_options={"visibility_timeout": visibility_timeout},
        result_expires=7 * 24 * 3600,
        task_serializer="json",
        result_serializer="json",
        accept_content=["json"],
        task_time_limit=settings.job_time_limit_seconds,
    )


def make_celery(settings: Settings | None = None) -> Celery:
    settings = settings or get_settings()
    app = Celery("denoiser", broker=settings.redis_url, backend=settings.redis_url, include=list(TASK_MODULES))
    app.conf.update(task_queues=[Queue(name) for name in QUEUES], **celery_config(settings))
    return app


app = make_celery()
