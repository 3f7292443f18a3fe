"""Bounds on request bodies: how many are taken in at once, and how long a client may pause while sending one.

Without them a client that declares 100 bytes and sends 1 holds a connection (and a task) forever, and many
large bodies buffered at once (session frames, up to DENOISER_MAX_FRAME_BYTES each) or unpacked at once (dataset
archives) exhaust memory and disk. Both answer at once instead of queueing: a full server says so (429 or 503
with Retry-After) and the client retries later.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from service.http.errors import ApiError

RETRY_AFTER_SECONDS = 1


class Slots:
    """At most ``capacity`` holders at once; ``take`` refuses the next one rather than make it wait."""

    def __init__(self, capacity: int, what: str, status: int, code: str) -> None:
        self.capacity = capacity
        self.what = what
        self.status = status
        self.code = code
        self.held = 0
        self._lock = threading.Lock()

    @contextmanager
    def take(self) -> Iterator[None]:
        with self._lock:
            if self.held >= self.capacity:
                raise ApiError(self.status, self.code, f"{self.held} {self.what} are in progress, the server's "
                                                       f"limit is {self.capacity}: retry in a moment",
                               {"limit": self.capacity}, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})
            self.held += 1
        try:
            yield
        finally:
            with self._lock:
                self.held -= 1


_slots: dict[tuple[str, int], Slots | ByteBudget] = {}
_slots_lock = threading.Lock()


def upload_slots(capacity: int) -> Slots:
    """The process's slots for dataset uploads (archives and frames): 429 when all are taken."""
    return _shared("uploads", capacity, lambda: Slots(capacity, "dataset uploads", 429, "too_many_uploads"))


class ByteBudget:
    """At most ``capacity`` bytes held at once by all holders; ``hold`` gives a holder whose ``add`` refuses
    (503 server_busy, Retry-After) the bytes that would pass it. A holder's bytes are freed when it exits."""

    def __init__(self, capacity: int, what: str) -> None:
        self.capacity = capacity
        self.what = what
        self.held = 0
        self._lock = threading.Lock()

    @contextmanager
    def hold(self) -> Iterator[Callable[[int], None]]:
        mine = 0

        def add(count: int) -> None:
            nonlocal mine
            with self._lock:
                if self.held + count > self.capacity:
                    raise ApiError(503, "server_busy", f"the server holds {self.held} bytes of {self.what} in "
                                                       f"progress, its limit is {self.capacity}: retry in a moment",
                                   {"limit_bytes": self.capacity}, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})
                self.held += count
                mine += count

        try:
            yield add
        finally:
            with self._lock:
                self.held -= mine


def frame_budget(capacity: int) -> ByteBudget:
    """The process's budget for session frame bodies in memory: 503 (the server is busy, not the caller wrong)."""
    return _shared("frames", capacity, lambda: ByteBudget(capacity, "session frames"))


def _shared(name: str, capacity: int, build):
    with _slots_lock:
        key = (name, capacity)
        if key not in _slots:
            _slots[key] = build()
        return _slots[key]


def body_timeout(timeout_seconds: float) -> ApiError:
    return ApiError(408, "body_timeout", f"the request body stalled: nothing arrived for {timeout_seconds:g} s; "
                                         f"send the whole body without pausing", {"timeout_seconds": timeout_seconds})


class BodyReadTimeout:
    """ASGI middleware: every read of a request's body waits at most ``timeout_seconds`` (then 408 body_timeout),
    for every route, JSON bodies included. Once the body is complete, reads pass through untimed (a streaming
    response waits on them for the client's disconnect)."""

    def __init__(self, app, timeout_seconds: float) -> None:
        self.app = app
        self.timeout_seconds = timeout_seconds

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        complete = False

        async def timed_receive():
            nonlocal complete
            if complete:
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.timeout_seconds)
            except asyncio.TimeoutError:
                raise body_timeout(self.timeout_seconds) from None
            if message["type"] != "http.request" or not message.get("more_body", False):
                complete = True
            return message

        await self.app(scope, timed_receive, send)
