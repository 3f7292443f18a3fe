"""The API's side of queueing: a producer-only Celery app on the workers' broker, sending jobs by task name
(``core.jobs.dispatch``), so the API process never imports the Celery task modules."""

from __future__ import annotations

from functools import lru_cache

from celery import Celery
from kombu import Queue

from core.jobs.dispatch import CeleryDispatcher, celery_config
from core.names import QUEUES
from core.settings import get_settings


@lru_cache(maxsize=1)
def producer() -> Celery:
    settings = get_settings()
    app = Celery("denoiser", broker=settings.redis_url, backend=settings.redis_url)
    app.conf.update(task_queues=[Queue(name) for name in QUEUES], **celery_config(settings))
    return app


def get_dispatcher() -> CeleryDispatcher:
    return CeleryDispatcher(producer())
