"""Recovery of jobs whose worker died, on the store directly (no process is killed)."""

from __future__ import annotations

import json
import time
import uuid
from datetime import datetime, timedelta, timezone

from workers.tasks.recovery import MAX_ATTEMPTS, recover_orphaned_jobs, waiting_task_ids


class Sent(list):
    def __call__(self, job_id: str, queue: str) -> None:
        self.append((job_id, queue))


def old(minutes: float = 10) -> datetime:
    return datetime.now(timezone.utc) - timedelta(minutes=minutes)


def running(store, owner: str | None = "worker", attempts: int = 1, **changes) -> str:
    job_id = store.create("train", {}, "cpu", "gpu", created_at=old())["id"]
    store.start(job_id, "worker")
    store.update(job_id, attempts=attempts, **changes)
    if owner is None:
        store.redis.delete(store.lease_key(job_id))  # its heartbeat stopped: the lease expired
    return job_id


def test_a_running_job_without_lease_is_sent_again_to_its_queue(store):
    orphan = running(store, owner=None)
    alive = running(store)
    sent = Sent()
    report = recover_orphaned_jobs(store, sent, waiting=set())
    assert report.resent == [orphan] and sent == [(orphan, "gpu")]
    assert store.get(orphan)["state"] == "queued" and store.get(alive)["state"] == "running"
    # Sent once: the next round finds it queued, fresh and (in real life) waiting in the queue.
    assert recover_orphaned_jobs(store, sent, waiting={orphan}).resent == [] and len(sent) == 1


def test_a_queued_job_is_resent_only_when_old_and_not_waiting(store):
    fresh = store.create("evaluate", {}, "cpu", "cpu")["id"]
    waiting = store.create("evaluate", {}, "cpu", "cpu", created_at=old())["id"]
    lost = store.create("evaluate", {}, "cpu", "cpu", created_at=old())["id"]
    store.redis.hset(store.key(waiting), "updated_at", json.dumps(old().isoformat()))
    store.redis.hset(store.key(lost), "updated_at", json.dumps(old().isoformat()))
    sent = Sent()
    report = recover_orphaned_jobs(store, sent, waiting={waiting})
    assert report.resent == [lost] and sent == [(lost, "cpu")]
    # Within the grace period even a message-less queued job is left alone (its message may be on its way).
    assert fresh not in report.resent
    later = time.time() + 3600
    assert fresh in recover_orphaned_jobs(store, Sent(), waiting=set(), now=later).resent


def test_a_job_lost_too_often_fails_and_a_cancelled_one_is_not_resent(store):
    doomed = running(store, owner=None, attempts=MAX_ATTEMPTS)
    cancelled = running(store, owner=None, cancel_requested=True)
    finished = running(store, owner=None)
    store.finish(finished, "succeeded")
    sent = Sent()
    report = recover_orphaned_jobs(store, sent, waiting=set())
    assert sent == [] and report.failed == [doomed] and report.cancelled == [cancelled]
    record = store.get(doomed)
    assert record["state"] == "failed" and record["error"]["code"] == "worker_lost"
    assert store.get(cancelled)["state"] == "cancelled" and store.get(finished)["state"] == "succeeded"


def test_waiting_task_ids_reads_kombu_messages_in_every_priority_list(store):
    queue = f"test-{uuid.uuid4().hex[:8]}"
    client = store.redis
    try:
        client.lpush(queue, json.dumps({"body": "", "headers": {"id": "a", "task": "x"}, "properties": {}}))
        client.lpush(f"{queue}\x06\x163", json.dumps({"headers": {"id": "b"}}))
        client.lpush(queue, "not json")
        assert waiting_task_ids(client, [queue, f"{queue}-empty"]) == {"a", "b"}
    finally:
        client.delete(queue, f"{queue}\x06\x163")
