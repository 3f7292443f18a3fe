"""The API's side of queueing: jobs sent by task name through the one Celery app (``core.celery_app``), whose task
modules only a worker imports."""

from __future__ import annotations

from core.jobs.dispatch import CeleryDispatcher


def get_dispatcher() -> CeleryDispatcher:
    # Imported at the first job, not with the app: the Celery app reads the settings when it is built.
    from core.celery_app import app

    return CeleryDispatcher(app)
