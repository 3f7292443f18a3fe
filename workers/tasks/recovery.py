"""Recovery of jobs whose worker died.

With Redis as the broker, a message that a killed worker had taken (late acks: unacknowledged) comes back only
after the visibility timeout, which is longer than any job (a day or more). So the workers recover such jobs
themselves: every worker, when it starts and then every ``RECOVERY_INTERVAL`` seconds, looks for jobs that are

- ``running`` without a lease (its execution's heartbeat stopped ``LEASE_TTL_SECONDS`` ago), or
- ``queued`` for more than ``QUEUED_GRACE_SECONDS`` without a lease and without a message waiting in a queue
  (the message was taken by a worker that died before starting the job),

and sends each one again under the same task id (a resumed training continues from its last checkpoint). A job
whose executions were lost ``MAX_ATTEMPTS`` times fails instead (``worker_lost``): it may be what kills its
workers. A job with a pending cancel is cancelled rather than resent. If the original message is redelivered
after all, the lease turns the duplicate away (``JobStore.start``).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import redis

from core.job_store import JobStore, age_seconds

RECOVERY_INTERVAL = 60.0
QUEUED_GRACE_SECONDS = 120.0
MAX_ATTEMPTS = 3
# kombu's Redis transport keeps priority p > 0 of queue Q in a list named Q + "\x06\x16" + p.
_PRIORITY_SEPARATOR = "\x06\x16"
_PRIORITIES = range(1, 10)

log = logging.getLogger("denoiser.recovery")

Send = Callable[[str, str], None]  # (job id, queue)


@dataclass
class RecoveryReport:
    resent: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    cancelled: list[str] = field(default_factory=list)


def waiting_task_ids(client: redis.Redis, queues: Iterable[str]) -> set[str]:
    """Task ids of the messages waiting in the broker's queue lists (not those taken by a worker)."""
    ids: set[str] = set()
    for queue in queues:
        for key in [queue] + [f"{queue}{_PRIORITY_SEPARATOR}{p}" for p in _PRIORITIES]:
            for raw in client.lrange(key, 0, -1):
                try:
                    ids.add(json.loads(raw)["headers"]["id"])
                except (ValueError, KeyError, TypeError):
                    continue  # not a Celery task message
    return ids


def recover_orphaned_jobs(store: JobStore, send: Send, waiting: set[str], *, now: float | None = None,
                          queued_grace: float = QUEUED_GRACE_SECONDS, max_attempts: int = MAX_ATTEMPTS
                          ) -> RecoveryReport:
    """Resend, fail or cancel every orphaned job (see the module notes); ``waiting``: ids already in a queue."""
    report = RecoveryReport()
    records, _ = store.list(limit=10**9)
    for record in records:
        job_id, state = record["id"], record["state"]
        if state not in ("queued", "running") or job_id in waiting or store.lease_holder(job_id) is not None:
            continue
        if state == "queued" and age_seconds(record["updated_at"], now) < queued_grace:
            continue
        if record["cancel_requested"]:
            store.finish(job_id, "cancelled")
            report.cancelled.append(job_id)
            continue
        if state == "running" and int(record["attempts"] or 0) >= max_attempts:
            store.finish(job_id, "failed", error={
                "code": "worker_lost",
                "message": f"the worker running this job was lost {record['attempts']} times; not retrying "
                           f"(the job may be what brings its workers down)"})
            report.failed.append(job_id)
            continue
        if store.requeue(job_id, state):
            send(job_id, record["queue"])
            report.resent.append(job_id)
            log.warning("job %s (%s, %s, attempt %s) had no live worker; sent it again to queue %s", job_id,
                        record["kind"], state, record["attempts"], record["queue"])
    return report
