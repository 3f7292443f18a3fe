"""The one Celery app: Redis broker and result backend, queues `cpu` and `gpu`, long-job settings.

Start a worker with `denoiser worker` (or `celery -A workers.celery_app worker -P solo -Q cpu`). The solo pool
runs tasks in the worker's main process, which is not daemonic, so a training task can start DDP ranks
(prefork children are daemonic and cannot have children of their own). The settings are shared with the API's
producer app (``core.jobs.dispatch.celery_config``).
"""

from __future__ import annotations

from celery import Celery
from kombu import Queue

from core.jobs.dispatch import celery_config
from core.names import QUEUES
from core.settings import get_settings

TASK_MODULES = ("workers.tasks.jobs",)


def make_celery() -> Celery:
    settings = get_settings()
    app = Celery("denoiser", broker=settings.redis_url, backend=settings.redis_url, include=list(TASK_MODULES))
    app.conf.update(task_queues=[Queue(name) for name in QUEUES], **celery_config(settings))
    return app


app = make_celery()
