"""The one Celery app: Redis broker and result backend, queues `cpu` and `gpu`, long-job settings.

Start a worker with `denoiser worker` (or `celery -A workers.celery_app worker -P solo -Q cpu`). The solo pool
runs tasks in the worker's main process, which is not daemonic, so a training task can start DDP ranks
(prefork children are daemonic and cannot have children of their own).
"""

from __future__ import annotations

from celery import Celery
from kombu import Queue

from service.settings import get_settings

QUEUES = ("cpu", "gpu")
TASK_MODULES = ("workers.tasks.jobs",)


def make_celery() -> Celery:
    settings = get_settings()
    # Longer than any job: Redis re-delivers an unacknowledged message only after this many seconds.
    visibility_timeout = settings.job_time_limit_seconds + 3600
    app = Celery("denoiser", broker=settings.redis_url, backend=settings.redis_url, include=list(TASK_MODULES))
    app.conf.update(
        task_queues=[Queue(name) for name in QUEUES],
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
    return app


app = make_celery()
