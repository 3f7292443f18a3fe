"""A running job rides out a Redis blip (retry with backoff, bounded) and still fails on a lasting outage."""

from __future__ import annotations

import pytest
import redis

from workers.redis_retry import with_retry
from tests.workers.tasks.fixtures import settings, storage  # noqa: F401 (fixtures)
from workers.tasks.context import JobContext


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


def failing(times: int, result="done"):
    calls = []

    def call():
        calls.append(1)
        if len(calls) <= times:
            raise redis.ConnectionError("Connection refused")
        return result

    return call, calls


def test_a_blip_is_retried_with_growing_delays():
    clock = FakeClock()
    call, calls = failing(3)
    assert with_retry(call, 20, "test", sleep=clock.sleep, clock=clock) == "done"
    assert len(calls) == 4 and clock.sleeps == [0.05, 0.1, 0.2]


def test_a_lasting_outage_raises_once_the_deadline_is_near():
    clock = FakeClock()
    call, calls = failing(10**6)
    with pytest.raises(redis.ConnectionError):
        with_retry(call, 5, "test", sleep=clock.sleep, clock=clock)
    assert clock.now <= 5 and max(clock.sleeps) <= 2.0 and len(calls) > 3


def test_other_errors_are_not_retried():
    def broken():
        raise redis.ResponseError("WRONGTYPE")

    with pytest.raises(redis.ResponseError):
        with_retry(broken, 20, "test", sleep=lambda s: pytest.fail("must not sleep"))


class BlippingStore:
    """A job store whose progress write fails ``times`` times, as during a 0.1 s Redis restart."""

    def __init__(self, times: int) -> None:
        self.failures = times
        self.reports: list[dict] = []

    def set_progress(self, job_id: str, report: dict) -> None:
        if self.failures:
            self.failures -= 1
            raise redis.ConnectionError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")
        self.reports.append(report)


def test_a_job_reporting_progress_through_a_redis_blip_goes_on(settings, storage):
    store, slept = BlippingStore(2), []
    record = {"id": "job-1", "params": {}, "device": "cpu"}
    context = JobContext(record, store, storage, settings, "me", sleep=slept.append)
    context.progress(1, 10, "step 1")  # before: ConnectionError here ended the attempt
    assert [r["current"] for r in store.reports] == [1] and slept == [0.05, 0.1]
