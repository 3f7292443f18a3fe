"""Sending jobs to the workers by task name: the API never imports the task modules, and core never imports Celery.

One Celery task, ``TASK_NAME``, runs every job; it takes the job id only (the record in Redis has the rest).
``CeleryDispatcher`` wraps any Celery app (the worker's own, or the API's producer-only one) and sends by that
name; ``celery_config`` is every setting the Celery apps share, as plain data.
"""

from __future__ import annotations

from typing import Any

from core.settings import Settings

TASK_NAME = "workers.tasks.jobs.run_job"  # defined there; only workers import it


class CeleryDispatcher:
    """How jobs are queued and revoked (a dependency, so tests can swap it)."""

    def __init__(self, celery: Any) -> None:
        self.celery = celery

    def send(self, job_id: str, queue: str) -> None:
        # run_job.apply_async by name (the API need not import the task's module): the task id is the job id, so
        # Celery's result (and a revoke) for the job are found by it.
        self.celery.send_task(TASK_NAME, args=[job_id], queue=queue, task_id=job_id)

    def revoke(self, job_id: str) -> None:
        # Workers drop a revoked message when it arrives; a worker that starts later does not know it, and the
        # job record (already cancelled) makes that execution return at once anyway.
        self.celery.control.revoke(job_id)


def celery_config(settings: Settings) -> dict[str, Any]:
    """The Celery configuration of the API's and the workers' apps (queues aside: ``core.names.QUEUES``)."""
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
