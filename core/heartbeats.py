"""Worker heartbeats in Redis: each worker writes its own key every few seconds; the API reads them.

Why not a Celery ping: a solo-pool worker answers control messages only between tasks, so while it trains it
looks dead and a readiness check built on the ping flapped. A thread in the worker writes
``denoiser:worker:<hostname>`` (JSON: hostname, pid, queues, the job it runs, when) with a TTL of a few intervals,
whatever the main thread is doing; a key that is gone means a worker that stopped beating.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from dataclasses import asdict, dataclass

import redis

KEY_PREFIX = "denoiser:worker:"
TTL_INTERVALS = 3  # a key outlives this many missed beats

log = logging.getLogger("denoiser.heartbeats")


@dataclass(frozen=True)
class WorkerBeat:
    hostname: str
    pid: int
    queues: list[str]
    job: str | None  # the job id it runs now, None when idle
    at: float  # time.time() of the beat


def write_beat(client: redis.Redis, beat: WorkerBeat, interval_seconds: float, prefix: str = KEY_PREFIX) -> None:
    client.set(f"{prefix}{beat.hostname}", json.dumps(asdict(beat)),
               ex=max(1, int(round(TTL_INTERVALS * interval_seconds))))


def read_beats(client: redis.Redis, prefix: str = KEY_PREFIX) -> list[WorkerBeat]:
    """Every worker whose heartbeat key is alive, by host name."""
    keys = sorted(client.scan_iter(match=f"{prefix}*", count=1000))
    beats = []
    for raw in client.mget(keys) if keys else []:
        if raw is None:
            continue  # expired since the scan
        try:
            beats.append(WorkerBeat(**json.loads(raw)))
        except (ValueError, TypeError):
            continue  # not written by this code
    return beats


class Heartbeat:
    """The beating thread of one worker process; ``job`` is what it reports running (set by the task)."""

    def __init__(self, client: redis.Redis, hostname: str, queues: list[str], interval_seconds: float,
                 prefix: str = KEY_PREFIX) -> None:
        self.client = client
        self.hostname = hostname
        self.queues = queues
        self.interval = interval_seconds
        self.prefix = prefix
        self.job: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="worker-heartbeat", daemon=True)

    def start(self) -> Heartbeat:
        """Write the first beat now (the worker is listed from its start), then beat on a thread."""
        self._beat_logged()
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        try:
            self.client.delete(f"{self.prefix}{self.hostname}")  # a clean stop is not a lost worker
        except redis.RedisError:
            pass

    def beat(self) -> None:
        write_beat(self.client, WorkerBeat(self.hostname, os.getpid(), self.queues, self.job, time.time()),
                   self.interval, self.prefix)

    def _beat_logged(self) -> None:
        try:
            self.beat()
        except redis.RedisError as error:  # Redis away for a moment: the next beat tries again
            log.warning("worker heartbeat not written: %s", error)

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._beat_logged()
