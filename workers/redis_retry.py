"""Riding out short Redis outages in a running job: a blip of a tenth of a second must not end a training attempt
(its retry recomputes up to ``checkpoint_every`` steps), while an outage that lasts stays an error.

``with_retry`` repeats a Redis call with exponential backoff until it succeeds or ``deadline_seconds`` have passed,
then raises the last error. Sleep and clock are arguments, so tests run it without waiting.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TypeVar

import redis

T = TypeVar("T")

FIRST_DELAY_SECONDS = 0.05
MAX_DELAY_SECONDS = 2.0
# What a Redis that is restarting or unreachable raises (Celery's result backend raises redis-py's errors too).
TRANSIENT_ERRORS = (redis.ConnectionError, redis.TimeoutError, ConnectionError, TimeoutError)

log = logging.getLogger("denoiser.jobs")


def with_retry(call: Callable[[], T], deadline_seconds: float, what: str, *,
               sleep: Callable[[float], None] = time.sleep, clock: Callable[[], float] = time.monotonic) -> T:
    started = clock()
    delay = FIRST_DELAY_SECONDS
    attempt = 1
    while True:
        try:
            return call()
        except TRANSIENT_ERRORS as error:
            waited = clock() - started
            if waited + delay > deadline_seconds:
                log.error("%s: Redis unreachable for %.1f s, giving up: %s", what, waited, error)
                raise
            log.warning("%s: Redis unreachable (attempt %d, %.1f s so far), retrying in %.2f s: %s", what, attempt,
                        waited, delay, error)
            sleep(delay)
            delay = min(delay * 2, MAX_DELAY_SECONDS)
            attempt += 1
