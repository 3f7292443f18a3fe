"""Sending jobs to the workers by task name, so the API never imports the task modules.

One Celery task, ``TASK_NAME``, runs every job; it takes the job id only (the record in Redis has the rest).
``CeleryDispatcher`` wraps the Celery app (``core.celery_app``, or a test's) and sends by that name.
"""

from __future__ import annotations

from typing import Any

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

