"""Job records in Redis: create, list, the start / cancel / finish transitions, leases."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone

import pytest

from tests.workers.tasks.fixtures import store  # noqa: F401  (fixture)
from core.job_store import EMPTY_PROGRESS, JobFinished, JobNotFound


def test_a_new_job_is_queued_with_every_field(store):
    record = store.create("train", {"dataset": "tiny", "steps": 3}, "gpu", "gpu")
    assert store.get(record["id"]) == record
    assert record["state"] == "queued" and record["attempts"] == 0 and record["progress"] == EMPTY_PROGRESS
    assert record["params"] == {"dataset": "tiny", "steps": 3} and record["queue"] == "gpu"
    assert record["started_at"] is None and record["error"] is None and record["cancel_requested"] is False
    assert store.get("missing") is None
    with pytest.raises(JobNotFound, match="'missing' does not exist"):
        store.require("missing")


def test_listing_is_newest_first_filtered_and_paged(store):
    start = datetime(2026, 1, 1, tzinfo=timezone.utc)
    ids = [store.create(kind, {}, "cpu", "cpu", created_at=start + timedelta(minutes=i))["id"]
           for i, kind in enumerate(["train", "evaluate", "train", "infer"])]
    records, total = store.list()
    assert [r["id"] for r in records] == ids[::-1] and total == 4
    records, total = store.list(kind="train")
    assert [r["id"] for r in records] == [ids[2], ids[0]] and total == 2
    records, total = store.list(limit=2, offset=1)
    assert [r["id"] for r in records] == [ids[2], ids[1]] and total == 4
    store.finish(ids[1], "succeeded", result={"ok": True})
    records, total = store.list(state="succeeded")
    assert [r["id"] for r in records] == [ids[1]] and total == 1


def test_start_takes_the_lease_and_turns_duplicates_away(store):
    job_id = store.create("evaluate", {}, "cpu", "cpu")["id"]
    decision = store.start(job_id, "worker-a")
    assert decision.started and decision.record["state"] == "running" and decision.record["attempts"] == 1
    assert store.lease_holder(job_id) == "worker-a" and store.get(job_id)["started_at"] is not None
    assert store.start(job_id, "worker-b").outcome == "busy"  # a duplicate delivery while it runs
    assert store.heartbeat(job_id, "worker-a") and not store.heartbeat(job_id, "worker-b")
    store.finish(job_id, "succeeded", result={"answer": 42})
    store.release(job_id, "worker-a")
    assert store.lease_holder(job_id) is None
    later = store.start(job_id, "worker-c")  # redelivered after it finished
    assert later.outcome == "finished" and later.record["result"] == {"answer": 42}
    assert store.lease_holder(job_id) is None
    assert store.start("missing", "worker-a").outcome == "missing"


def test_a_restart_after_a_lost_lease_counts_an_attempt_and_keeps_the_first_start(store):
    job_id = store.create("train", {}, "cpu", "cpu")["id"]
    first = store.start(job_id, "worker-a").record
    store.redis.delete(store.lease_key(job_id))  # the lease expired: worker-a died
    assert store.requeue(job_id, "running") and store.get(job_id)["state"] == "queued"
    second = store.start(job_id, "worker-b").record
    assert second["attempts"] == 2 and second["started_at"] == first["started_at"]


def test_cancel_ends_a_queued_job_at_once_and_flags_a_running_one(store):
    queued = store.create("train", {}, "cpu", "cpu")["id"]
    record = store.request_cancel(queued)
    assert record["state"] == "cancelled" and record["finished_at"] and record["cancel_requested"]
    assert store.start(queued, "worker").outcome == "finished"
    with pytest.raises(JobFinished, match="already finished \\(cancelled\\)"):
        store.request_cancel(queued)

    running = store.create("train", {}, "cpu", "cpu")["id"]
    store.start(running, "worker")
    record = store.request_cancel(running)
    assert record["state"] == "running" and store.cancel_requested(running)
    assert store.finish(running, "cancelled")["state"] == "cancelled"
    assert store.finish(running, "succeeded")["state"] == "cancelled"  # the first end stays
    with pytest.raises(JobNotFound):
        store.request_cancel("missing")


def test_a_cancel_that_arrives_between_queue_and_start_wins(store):
    job_id = store.create("train", {}, "cpu", "cpu")["id"]
    store.update(job_id, cancel_requested=True)
    decision = store.start(job_id, "worker")
    assert decision.outcome == "cancelled" and store.get(job_id)["state"] == "cancelled"
    assert store.lease_holder(job_id) is None


def test_update_never_resurrects_a_deleted_job_and_rejects_unknown_fields(store):
    job_id = store.create("infer", {}, "cpu", "cpu")["id"]
    store.delete(job_id)
    store.set_progress(job_id, {"current": 1, "total": 2, "message": "", "eta_seconds": None})
    assert store.get(job_id) is None and store.ids() == []
    with pytest.raises(ValueError, match="unknown job record fields: colour"):
        store.update(job_id, colour="red")
