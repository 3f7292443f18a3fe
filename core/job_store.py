"""Job records in Redis: what the API shows for a job and how API and worker agree on its state.

Keys (``prefix`` is ``denoiser:`` outside tests):

    {prefix}job:<id>             hash, one JSON-encoded value per field (id, kind, state, params, device, queue,
                                 created_at, started_at, finished_at, progress, mlflow_run_id, mlflow_url,
                                 result, error, attempts, cancel_requested, updated_at)
    {prefix}job:<id>:lease       the running execution's owner ("host:pid:token"), with a short TTL that the
                                 execution's heartbeat thread keeps refreshing: no lease = nobody runs the job
    {prefix}jobs                 sorted set of job ids scored by creation time (listing, newest first)

The record, not Celery's result backend, is the truth about a job: the API writes it on submit and cancel, the
worker on start, progress and end. Transitions that both sides make (start, cancel, finish) run in WATCH/MULTI
transactions, so a cancel racing a start ends in exactly one consistent state.

Leases make duplicate deliveries harmless: an execution starts only by taking the lease (SET NX), so a second
delivery of a job that is running elsewhere, or that finished, returns at once (``start`` says why).
"""

from __future__ import annotations

import json
import os
import socket
import time
import uuid
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

import redis

from core.names import FINISHED_STATES, JOB_KINDS, JOB_STATES

DEFAULT_PREFIX = "denoiser:"
LEASE_TTL_SECONDS = 30  # a killed worker's job counts as orphaned this long after its last heartbeat
EMPTY_PROGRESS = {"current": 0, "total": 0, "message": "", "eta_seconds": None}
FIELDS = ("id", "kind", "state", "params", "device", "queue", "created_at", "started_at", "finished_at",
          "progress", "mlflow_run_id", "mlflow_url", "result", "error", "attempts", "cancel_requested",
          "updated_at")


class JobNotFound(KeyError):
    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class JobFinished(RuntimeError):
    """A change that needs an unfinished job (cancel) was asked of a finished one; ``state`` says how it ended."""

    def __init__(self, job_id: str, state: str) -> None:
        super().__init__(f"job {job_id!r} has already finished ({state})")
        self.state = state
        self.details = {"state": state}


def utc_now() -> str:
    return datetime.now(timezone.utc).isoformat()


def new_job_id() -> str:
    return uuid.uuid4().hex


def execution_owner() -> str:
    """Who holds a lease: host and pid (readable in Redis when debugging) plus a token unique to the execution."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


@dataclass(frozen=True)
class StartDecision:
    """What ``JobStore.start`` decided: ``started`` (the caller runs the job) or why not."""

    outcome: str  # started | missing | finished | cancelled | busy
    record: dict[str, Any] | None

    @property
    def started(self) -> bool:
        return self.outcome == "started"


class JobStore:
    def __init__(self, client: redis.Redis, prefix: str = DEFAULT_PREFIX) -> None:
        self.redis = client
        self.prefix = prefix

    @classmethod
    def from_url(cls, url: str, prefix: str = DEFAULT_PREFIX) -> JobStore:
        return cls(redis.Redis.from_url(url, decode_responses=True), prefix)

    # ------------------------------------------------------------------------------------------ keys

    def key(self, job_id: str) -> str:
        return f"{self.prefix}job:{job_id}"

    def lease_key(self, job_id: str) -> str:
        return f"{self.prefix}job:{job_id}:lease"

    @property
    def index_key(self) -> str:
        return f"{self.prefix}jobs"

    # ----------------------------------------------------------------------------------- encoding

    @staticmethod
    def _encode(values: dict[str, Any]) -> dict[str, str]:
        unknown = set(values) - set(FIELDS)
        if unknown:
            raise ValueError(f"unknown job record fields: {', '.join(sorted(unknown))}")
        return {name: json.dumps(value) for name, value in values.items()}

    @staticmethod
    def _decode(raw: dict[str, str]) -> dict[str, Any] | None:
        if not raw:
            return None
        record = {name: None for name in FIELDS}
        record.update({name: json.loads(value) for name, value in raw.items() if name in record})
        return record

    # ------------------------------------------------------------------------------------- create, read

    def create(self, kind: str, params: dict[str, Any], device: str, queue: str, job_id: str | None = None,
               created_at: datetime | None = None) -> dict[str, Any]:
        if kind not in JOB_KINDS:
            raise ValueError(f"unknown job kind {kind!r}")
        job_id = job_id or new_job_id()
        created = created_at or datetime.now(timezone.utc)
        record = {"id": job_id, "kind": kind, "state": "queued", "params": params, "device": device, "queue": queue,
                  "created_at": created.isoformat(), "started_at": None, "finished_at": None,
                  "progress": dict(EMPTY_PROGRESS), "mlflow_run_id": None, "mlflow_url": None, "result": None,
                  "error": None, "attempts": 0, "cancel_requested": False, "updated_at": created.isoformat()}
        pipe = self.redis.pipeline()
        pipe.hset(self.key(job_id), mapping=self._encode(record))
        pipe.zadd(self.index_key, {job_id: created.timestamp()})
        pipe.execute()
        return record

    def get(self, job_id: str) -> dict[str, Any] | None:
        return self._decode(self.redis.hgetall(self.key(job_id)))

    def require(self, job_id: str) -> dict[str, Any]:
        record = self.get(job_id)
        if record is None:
            raise JobNotFound(f"job {job_id!r} does not exist")
        return record

    def ids(self) -> list[str]:
        """Every job id, newest first."""
        return self.redis.zrevrange(self.index_key, 0, -1)

    def list(self, kind: str | None = None, state: str | None = None, limit: int = 50,
             offset: int = 0) -> tuple[list[dict[str, Any]], int]:
        """(one page of records, total matching), newest first. Filters run over the records (the index is one
        sorted set): fine for the thousands of jobs one service keeps."""
        ids = self.ids()
        pipe = self.redis.pipeline()
        for job_id in ids:
            pipe.hgetall(self.key(job_id))
        records = [r for r in (self._decode(raw) for raw in pipe.execute()) if r is not None]
        matching = [r for r in records
                    if (kind is None or r["kind"] == kind) and (state is None or r["state"] == state)]
        return matching[offset:offset + limit], len(matching)

    def counts(self) -> dict[tuple[str, str], int]:
        """(kind, state) -> how many job records there are, for every kind and state (zeros included); two
        fields per record, not whole records (the API's /metrics asks at every scrape)."""
        counts = {(kind, state): 0 for kind in JOB_KINDS for state in JOB_STATES}
        pipe = self.redis.pipeline()
        for job_id in self.ids():
            pipe.hmget(self.key(job_id), ["kind", "state"])
        for kind, state in pipe.execute():
            if kind is None or state is None:
                continue  # deleted since the index was read
            key = (json.loads(kind), json.loads(state))
            counts[key] = counts.get(key, 0) + 1
        return counts

    # ------------------------------------------------------------------------------------ updates

    def update(self, job_id: str, **values: Any) -> None:
        """Set fields of an existing record (a record deleted meanwhile is not brought back)."""
        values["updated_at"] = utc_now()
        encoded = self._encode(values)

        def change(pipe: redis.client.Pipeline) -> None:
            if not pipe.exists(self.key(job_id)):
                return
            pipe.multi()
            pipe.hset(self.key(job_id), mapping=encoded)

        self.redis.transaction(change, self.key(job_id))

    def set_progress(self, job_id: str, progress: dict[str, Any]) -> None:
        self.update(job_id, progress=progress)

    def _transition(self, job_id: str, decide) -> Any:
        """Run ``decide(record) -> (changes or None, answer)`` atomically on the record; returns the answer."""
        answer: list[Any] = []

        def change(pipe: redis.client.Pipeline) -> None:
            answer.clear()
            record = self._decode(pipe.hgetall(self.key(job_id)))
            changes, result = decide(record)
            answer.append(result)
            pipe.multi()
            if changes:
                pipe.hset(self.key(job_id), mapping=self._encode({**changes, "updated_at": utc_now()}))

        self.redis.transaction(change, self.key(job_id))
        return answer[0]

    # ---------------------------------------------------------------------------- worker side

    def start(self, job_id: str, owner: str, ttl: int = LEASE_TTL_SECONDS) -> StartDecision:
        """Take the job's lease and mark it running, or say why this execution must not run it."""
        record = self.get(job_id)
        if record is None:
            return StartDecision("missing", None)
        if record["state"] in FINISHED_STATES:
            return StartDecision("finished", record)
        if not self.redis.set(self.lease_key(job_id), owner, nx=True, ex=ttl):
            return StartDecision("busy", record)

        def decide(current):
            if current is None:
                return None, StartDecision("missing", None)
            if current["state"] in FINISHED_STATES:
                return None, StartDecision("finished", current)
            now = utc_now()
            if current["cancel_requested"]:
                changes = {"state": "cancelled", "finished_at": now}
                return changes, StartDecision("cancelled", {**current, **changes})
            changes = {"state": "running", "started_at": current["started_at"] or now,
                       "attempts": int(current["attempts"] or 0) + 1, "error": None}
            return changes, StartDecision("started", {**current, **changes})

        decision = self._transition(job_id, decide)
        if not decision.started:
            self.release(job_id, owner)
        return decision

    def heartbeat(self, job_id: str, owner: str, ttl: int = LEASE_TTL_SECONDS) -> bool:
        """Extend the lease; False when another execution holds it now (this one should stop)."""
        key = self.lease_key(job_id)

        def extend(pipe: redis.client.Pipeline) -> bool:
            holder = pipe.get(key)
            pipe.multi()
            if holder in (None, owner):
                pipe.set(key, owner, ex=ttl)
            return holder in (None, owner)

        return self.redis.transaction(extend, key, value_from_callable=True)

    def release(self, job_id: str, owner: str) -> None:
        key = self.lease_key(job_id)

        def drop(pipe: redis.client.Pipeline) -> None:
            holder = pipe.get(key)
            pipe.multi()
            if holder == owner:
                pipe.delete(key)

        self.redis.transaction(drop, key)

    def lease_holder(self, job_id: str) -> str | None:
        return self.redis.get(self.lease_key(job_id))

    def finish(self, job_id: str, state: str, *, result: dict[str, Any] | None = None,
               error: dict[str, str] | None = None, progress: dict[str, Any] | None = None) -> dict[str, Any] | None:
        """End the job in ``state`` (unless it ended already); returns the final record."""
        if state not in FINISHED_STATES:
            raise ValueError(f"{state!r} is not a final state")

        def decide(current):
            if current is None or current["state"] in FINISHED_STATES:
                return None, current
            changes = {"state": state, "finished_at": utc_now(), "error": error}
            if result is not None:
                changes["result"] = result
            if progress is not None:
                changes["progress"] = progress
            return changes, {**current, **changes}

        return self._transition(job_id, decide)

    # -------------------------------------------------------------------------------- API side

    def request_cancel(self, job_id: str) -> dict[str, Any]:
        """Flag the job for cancellation; a job nobody has started yet ends as cancelled right away.

        Raises JobNotFound, or JobFinished for a job that already ended.
        """

        def decide(current):
            if current is None:
                raise JobNotFound(f"job {job_id!r} does not exist")
            if current["state"] in FINISHED_STATES:
                raise JobFinished(job_id, current["state"])
            changes: dict[str, Any] = {"cancel_requested": True}
            if current["state"] == "queued":
                changes.update(state="cancelled", finished_at=utc_now())
            return changes, {**current, **changes}

        return self._transition(job_id, decide)

    def cancel_requested(self, job_id: str) -> bool:
        value = self.redis.hget(self.key(job_id), "cancel_requested")
        return bool(value and json.loads(value))

    # ---------------------------------------------------------------------------------- recovery

    def requeue(self, job_id: str, expected_state: str) -> bool:
        """An orphaned job (no lease) back to ``queued``, if it is still in ``expected_state`` and still unleased."""

        def decide(current):
            if current is None or current["state"] != expected_state or self.lease_holder(job_id) is not None:
                return None, False
            return {"state": "queued"}, True

        return self._transition(job_id, decide)

    def delete(self, job_id: str) -> None:
        pipe = self.redis.pipeline()
        pipe.delete(self.key(job_id), self.lease_key(job_id))
        pipe.zrem(self.index_key, job_id)
        pipe.execute()


def age_seconds(timestamp: str | None, now: float | None = None) -> float:
    if not timestamp:
        return float("inf")
    return (now if now is not None else time.time()) - datetime.fromisoformat(timestamp).timestamp()


def get_job_store() -> JobStore:
    """The store of the configured Redis (one client per URL, shared: redis-py clients are thread-safe pools)."""
    from core.settings import get_settings

    return store_for(get_settings().redis_url)


_stores: dict[str, JobStore] = {}


def store_for(url: str) -> JobStore:
    if url not in _stores:
        _stores[url] = JobStore.from_url(url)
    return _stores[url]
