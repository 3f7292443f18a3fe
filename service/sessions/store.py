"""Inference sessions: a registered model plus one stream's temporal history, kept between frame requests.

A session runs ``method.step(frame, state)`` once per posted frame, carrying ``state`` from frame to frame exactly as
training and evaluation do, so a stream sent frame by frame gives what the method gives in process. Frames come in
``frame_index`` order (a gap restarts the history or is refused, by ``on_gap``; a step backwards is refused), at the
render resolution of the first frame since the last reset.

Sessions live in memory and are mirrored to Redis (one hash per session: its metadata and its state as
``service.sessions.state_codec`` chunks, replaced whole in one transaction), so a restarted API process continues each
live session from its last mirrored frame, and Redis is the record of which sessions exist. A frame's mirror is
written by a background writer while the next step runs: Redis is at most one frame behind memory. Several API
processes may serve one session in turn (replicas behind a proxy): each mirror names the process that wrote it, a
memory copy is used only while Redis holds its own lineage, and a write lands only over the revision its copy
continues (compare-and-set), so no process steps a session from, or writes back, a copy another one has moved
past. Every step, weight load and history restore runs on the store's torch threads
(``service.sessions.torch_thread``). The frame rules, the mirror's timing and what a crash loses:
docs/architecture.md, "service.sessions.store"; replicas: docs/operations.md, "API replicas".
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import logging
import os
import re
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, NamedTuple, TypeVar

import numpy as np
import redis
import torch
from redis.backoff import NoBackoff
from redis.retry import Retry

from model.io.frames import FrameBundle
from model.deployment.inference_forms import load_form_table
from model.methods.base import FrameBatch, Method, State
from model.io.sanitize import SanitizeReport, sanitize_frame
from service.sessions.metrics import MIRROR_DELETE, MIRROR_WRITE, SessionMetrics
from service.sessions.state_codec import CompressionMemo, StateFormatError, decode_state, encode_state
from core.registry import Registry, UnknownModelError, registry_for
from service.sessions.models import (
    REGISTERED,
    SessionModelSource,
    load_session_method,
    registered_checkpoint,
    resolve_session_model,
)
from core.settings import Settings
from service.sessions.torch_thread import TorchPool, set_own_torch_threads

log = logging.getLogger("denoiser.sessions")
T = TypeVar("T")

KEY_PREFIX = "denoiser:session:"
DELETED_SUFFIX = "-deleted:"  # + session id: a deleted session's marker, so no other process writes it back
ON_GAP_POLICIES = ("reset", "reject")
SESSION_ID = re.compile(r"^[0-9a-f]{32}$")
REDIS_PAUSE_SECONDS = 5.0  # after a Redis failure, serve from memory this long before trying Redis again
MIRROR_WRITERS = 4  # threads writing frames' mirrors to Redis (each session's writes stay in order, one at a time)
STATE_CHUNK_BYTES = 32 * 1024 * 1024  # one Redis field each: no single command buffers a whole 1080p history

# X-History values: what happened to the history before this frame.
STARTED, CONTINUED, RESET_GAP, RESET_CAMERA_CUT = "started", "continued", "reset-gap", "reset-camera-cut"


class SessionError(Exception):
    """A session request the store refuses; ``code`` and ``details`` go into the API's error body."""

    code = "session_error"

    def __init__(self, message: str, code: str | None = None, details: Any = None) -> None:
        super().__init__(message)
        self.message = message
        self.code = code or self.code
        self.details = details


class SessionNotFound(SessionError):
    code = "not_found"


class SessionLimitReached(SessionError):
    code = "too_many_sessions"


class FrameRejected(SessionError):
    """The frame does not fit the session: frame_gap, frame_out_of_order or resolution_mismatch."""


class SessionStoreUnavailable(SessionError):
    code = "session_store_unavailable"


class ModelNotLoadable(SessionError):
    """The registered checkpoint cannot be turned into a method here (unknown method, damaged file)."""

    code = "model_not_loadable"


def token_digest(token: str) -> str:
    """What a session keeps of its owner token (the token itself is only ever in the creation's answer)."""
    return hashlib.sha256(token.encode()).hexdigest()


@dataclass(frozen=True)
class SessionModel:
    name: str
    version: str | None  # registered: the version; pretrained: its file's sha256 prefix; method: None
    alias: str | None
    method: str
    preset: str
    scale: int
    params: int
    # Sessions created with model "auto": the choice (core.registry.AutoChoice.to_dict) that picked this version.
    choice: dict[str, Any] | None = field(default=None, compare=False)
    source: str = REGISTERED  # registered, pretrained or method (service.sessions.models)

    @property
    def origin(self) -> SessionModelSource:
        return SessionModelSource(self.source, self.name, self.version, self.scale)

    def describe(self) -> str:
        if self.source == REGISTERED:
            return f"version {self.version} of model {self.name!r}"
        return f"{self.source} {self.name!r}"


@dataclass(frozen=True)
class MirrorState:
    """A session's Redis mirror: ``current`` when Redis holds its newest revision; ``last_written_frame``: the last
    frame whose history Redis holds (None: none, a new or reset session); ``pending_since``: when Redis started
    lacking the newest revision (seconds since the epoch; None while current)."""

    current: bool
    last_written_frame: int | None
    pending_since: float | None


@dataclass
class Session:
    id: str
    model: SessionModel
    on_gap: str
    created_at: float  # seconds since the epoch
    last_used_at: float
    ttl_seconds: int
    frames_processed: int = 0
    next_frame_index: int | None = None  # None: no history, the next frame starts one
    resolution: tuple[int, int] | None = None  # (width, height) at render resolution
    revision: int = 0
    # SHA-256 of the owner token given at creation (DENOISER_SESSION_OWNER_TOKENS), None: any key holder drives it.
    owner_digest: str | None = None
    layout: str | dict[str, Any] = "denoiser"  # how posted frames are read (model.layouts.layout_from_value)
    # Runtime only (not in the metadata):
    state: State | None = field(default=None, repr=False)
    method: Method | None = field(default=None, repr=False)
    mirrored_revision: int = field(default=-1, repr=False)  # the revision Redis holds, as far as we know
    mirrored_frame: int | None = field(default=None, repr=False)  # the last frame whose history Redis holds
    # Since when (seconds since the epoch) Redis has lacked the newest revision; None while it holds it.
    mirror_behind_since: float | None = field(default=None, repr=False)
    # The writer tag ("<process>:<revision>") of the revision this copy was loaded from or last wrote to Redis: its
    # next write lands only over that one (None: a new session, whose key must not exist yet).
    mirror_tag: str | None = field(default=None, repr=False)
    # The tag of the revision this copy was loaded from (None: made in this process), which Redis may still show
    # to a read that started before this copy's first write landed.
    origin_tag: str | None = field(default=None, repr=False)
    # Redis refused this copy's write: another process moved the session on (or deleted it); never step it again.
    superseded: bool = field(default=False, repr=False)
    # Used only by the session's mirror writer, one write at a time.
    codec_memo: CompressionMemo = field(default_factory=CompressionMemo, repr=False)

    @property
    def expires_at(self) -> float:
        return self.last_used_at + self.ttl_seconds

    def expired(self, now: float) -> bool:
        return now >= self.expires_at

    def mirror_state(self) -> MirrorState:
        """Whether Redis holds this revision (what a restarted API would continue from)."""
        current = self.mirrored_revision >= self.revision
        return MirrorState(current, self.mirrored_frame, None if current else self.mirror_behind_since)

    def metadata(self) -> dict[str, Any]:
        return {"id": self.id, "model": self.model.__dict__, "on_gap": self.on_gap, "created_at": self.created_at,
                "last_used_at": self.last_used_at, "frames_processed": self.frames_processed,
                "next_frame_index": self.next_frame_index,
                "resolution": list(self.resolution) if self.resolution else None, "revision": self.revision,
                "owner_digest": self.owner_digest, "layout": self.layout}

    @classmethod
    def from_metadata(cls, meta: dict[str, Any], ttl_seconds: int, mirror_tag: str | None = None) -> Session:
        """The session as Redis holds it (so its mirror is current); ``mirror_tag``: the hash's writer tag."""
        frame = meta["next_frame_index"] - 1 if meta["next_frame_index"] is not None else None
        return cls(mirrored_revision=meta["revision"], mirrored_frame=frame, mirror_tag=mirror_tag,
                   origin_tag=mirror_tag,
                   id=meta["id"], model=SessionModel(**meta["model"]), on_gap=meta["on_gap"],
                   created_at=meta["created_at"], last_used_at=meta["last_used_at"], ttl_seconds=ttl_seconds,
                   frames_processed=meta["frames_processed"], next_frame_index=meta["next_frame_index"],
                   resolution=tuple(meta["resolution"]) if meta["resolution"] else None, revision=meta["revision"],
                   owner_digest=meta.get("owner_digest"), layout=meta.get("layout", "denoiser"))


@dataclass(frozen=True)
class ReadFrame:
    """A frame read straight into its batch (a stream message, by ``SessionStore.read_frame``): what the frame
    rules need and the batch on the session device; ``plainly_valid``: the read proved the input check would
    repair nothing (service.sessions.stream_batch), so the step skips it; ``output_dtype``: "float32" or "float16", the
    output's dtype (the stream's answer is packed in it: torch casts it on the step's thread, faster than NumPy)."""

    frame_index: int
    width: int
    height: int
    camera_cut: bool
    batch: FrameBatch = field(repr=False)
    plainly_valid: bool = False
    output_dtype: str = "float32"


@dataclass(frozen=True)
class FrameResult:
    output: np.ndarray  # (H * scale, W * scale, 3) float32, a view of (3, H * scale, W * scale) planes of its own
    frame_index: int
    history: str  # STARTED, CONTINUED, RESET_GAP or RESET_CAMERA_CUT
    inference_ms: float  # method.step alone
    sanitized: SanitizeReport  # NaN / Inf / out-of-range input pixels repaired before the step
    session: Session


class _PlannedFrame(NamedTuple):
    """A frame as the session's frame rules take it: its index filled in, its resolution, the X-History label and
    the state its step continues."""

    frame: FrameBundle | ReadFrame
    resolution: tuple[int, int]
    history: str
    state: State | None


_Stepped = tuple[np.ndarray, State, float, SanitizeReport]  # what SessionStore._step returns


def state_fields(data: bytes, chunk_bytes: int = STATE_CHUNK_BYTES) -> dict[str, bytes | int]:
    """Encoded state -> the Redis hash fields that hold it: ``state_chunks`` and ``state.<i>``."""
    chunks = [data[start:start + chunk_bytes] for start in range(0, len(data), chunk_bytes)]
    return {"state_chunks": len(chunks), **{f"state.{index}": chunk for index, chunk in enumerate(chunks)}}


def state_from_fields(fields: dict[bytes, bytes], device: torch.device | str = "cpu") -> State | None:
    """The inverse of ``state_fields`` (a hash as HGETALL returns it); StateFormatError if chunks are missing."""
    if b"state_chunks" not in fields and fields.get(b"state"):
        # Written by a version before the chunked format (a session live across the upgrade): torch.save bytes.
        return torch.load(io.BytesIO(fields[b"state"]), map_location=device, weights_only=True)
    count = int(fields.get(b"state_chunks", b"0"))
    missing = [index for index in range(count) if f"state.{index}".encode() not in fields]
    if missing:
        raise StateFormatError(f"the stored history lacks chunk(s) {missing} of {count}")
    return decode_state(b"".join(fields[f"state.{index}".encode()] for index in range(count)), device)


@dataclass(frozen=True)
class _Snapshot:
    """One revision of a session as Redis is to hold it: metadata taken when handed over, the state tensors by
    reference (nothing changes them: a step makes a new state and never alters the one it is given)."""

    session: Session
    revision: int
    meta: str
    state: State | None
    frame: int | None = None  # the last frame this history follows (None: no history)
    tag: str = ""  # the writer tag this revision gets in Redis


def _daemon_timer(delay: float, function: Callable[[], None]) -> threading.Timer:
    timer = threading.Timer(delay, function)
    timer.daemon = True
    timer.start()
    return timer


class _MirrorWriter:
    """One session's background writer: writes the newest snapshot handed to it, one write at a time.

    A snapshot handed over with ``start=False`` waits for ``start()`` (the API starts it once the response is
    sent, so the write does not compete with the response for the CPU) or for anyone waiting on the writer.
    With ``min_interval`` > 0, ``start()`` begins a write at most once per ``min_interval`` seconds; a snapshot
    handed over sooner waits (newer ones replace it) and is written when the interval is over, by a timer if no
    other call comes; ``wait()`` writes at once.

    A write that fails (``write`` returns False) is kept and retried after ``retry_delay()`` seconds, by a timer,
    until it lands, so an idle session's history reaches Redis once it is back; ``retry()`` tries it at once. A
    newer snapshot replaces it; ``discard()`` and ``close()`` drop it, so no late retry brings a session back.
    """

    def __init__(self, write: Callable[[_Snapshot], bool], executor: ThreadPoolExecutor,
                 min_interval: float = 0.0, monotonic: Callable[[], float] = time.monotonic,
                 timer: Callable[[float, Callable[[], None]], Any] | None = None,
                 retry_delay: Callable[[], float] = lambda: REDIS_PAUSE_SECONDS) -> None:
        self._write = write
        self._executor = executor
        # Injectable so a test drives the interval by construction (a fake clock, a timer it fires itself).
        self._monotonic = monotonic
        self._start_timer = timer or _daemon_timer
        self._condition = threading.Condition()
        self._pending: _Snapshot | None = None
        self._running = False
        self._min_interval = min_interval
        self._not_before = 0.0  # time.monotonic() before which start() defers a write
        self._timer: threading.Timer | None = None
        self._forced = 0  # callers of wait() waiting: their writes are not deferred
        self._retry_delay = retry_delay
        self._failed: _Snapshot | None = None  # the newest snapshot whose write failed, until one lands
        self._retry_timer: Any = None
        self._closed = False  # discarded or closed: nothing is written any more

    def submit(self, snapshot: _Snapshot, start: bool = True) -> None:
        with self._condition:
            if self._closed:
                return
            self._pending = snapshot  # an older one not started yet is superseded: Redis wants the newest
        if start:
            self.start()

    def start(self) -> None:
        """Write the pending snapshot in the background, unless there is none, a write is running (which then
        writes it next) or the minimum interval since the last write is not over (a timer starts it then)."""
        with self._condition:
            if self._closed or self._running or self._pending is None or self._defer():
                return
            self._running = True
        try:
            self._executor.submit(self._drain)
        except RuntimeError:  # the pool is shut down (the store is closing): write here
            self._drain()

    def wait(self, timeout: float | None = None) -> bool:
        """Until nothing is pending or being written (a held or deferred snapshot is started); False on
        ``timeout``."""
        with self._condition:
            self._forced += 1
        try:
            self.start()
            with self._condition:
                return self._condition.wait_for(
                    lambda: self._pending is None and not self._running, timeout)
        finally:
            with self._condition:
                self._forced -= 1

    def retry(self) -> None:
        """Write the snapshot whose write failed now (in the background), unless a newer one replaced it."""
        with self._condition:
            if self._closed or self._failed is None:
                return
            if self._pending is None:  # a pending snapshot is newer: it wins
                self._pending = self._failed
            self._failed = None
            if self._retry_timer is not None:
                self._retry_timer.cancel()
                self._retry_timer = None
        self.start()

    @property
    def failed(self) -> bool:
        with self._condition:
            return self._failed is not None

    def drop_failed(self) -> None:
        """Give up the failed write (Redis holds a newer revision, written by another API process)."""
        with self._condition:
            self._failed = None

    def discard(self) -> None:
        """Drop pending and failed writes and wait for one in progress (the session is being deleted)."""
        self.close()
        with self._condition:
            self._condition.wait_for(lambda: not self._running)

    def close(self) -> None:
        """Write nothing more: drop pending and failed writes and stop their timers (without waiting)."""
        with self._condition:
            self._closed = True
            self._pending = self._failed = None
            for timer in (self._timer, self._retry_timer):
                if timer is not None:
                    timer.cancel()
            self._timer = self._retry_timer = None
            self._condition.notify_all()

    def _retry_due(self) -> None:
        with self._condition:
            self._retry_timer = None
        self.retry()

    def _defer(self) -> bool:
        """(Under the lock.) Whether the pending write must wait for the interval; if so, a timer will start it."""
        delay = self._not_before - self._monotonic()
        if self._forced or delay <= 0:
            return False
        if self._timer is None:
            self._timer = self._start_timer(delay, self._interval_over)
        return True

    def _interval_over(self) -> None:
        with self._condition:
            self._timer = None
        self.start()

    def _drain(self) -> None:
        while True:
            with self._condition:
                snapshot = None if self._pending is None or self._defer() else self._pending
                if snapshot is None:
                    self._running = False
                    self._condition.notify_all()
                    return
                self._pending = None
                self._not_before = self._monotonic() + self._min_interval
            try:
                written = self._write(snapshot)
            except Exception:  # never leave the writer marked running: the session would wait forever
                log.exception("session %s: writing its mirror failed", snapshot.session.id)
                written = False
            with self._condition:
                if written:
                    if self._failed is not None and self._failed.revision <= snapshot.revision:
                        self._failed = None
                elif not self._closed:
                    # A newer pending snapshot replaces this one (and any older failure).
                    self._failed = snapshot if self._pending is None else None
                    if self._retry_timer is None:
                        self._retry_timer = self._start_timer(self._retry_delay(), self._retry_due)


class SessionStore:
    """Every live session of this API process, mirrored to Redis (see the module notes)."""

    def __init__(self, settings: Settings, *, registry: Registry | None = None,
                 redis_client: redis.Redis | None = None, prefix: str | None = None,
                 clock: Callable[[], float] = time.time,
                 mirror_timing: tuple[Callable[[], float], Callable[[float, Callable[[], None]], Any]] | None = None
                 ) -> None:
        """``mirror_timing``: (monotonic clock, timer starter) of the mirror writers' interval; tests only."""
        self.mirror_timing = mirror_timing or (time.monotonic, _daemon_timer)
        self.ttl_seconds = settings.session_ttl_seconds
        self.mirror_interval = settings.session_mirror_interval_seconds
        self.history_precision = settings.session_history_precision
        self.forms = load_form_table(settings.inference_forms)
        self.max_sessions = settings.max_sessions
        self.device = torch.device(settings.session_device)
        self.prefix = prefix or KEY_PREFIX
        # Names this process in the writer tag of every mirror it writes (several API replicas share Redis).
        self.instance = uuid.uuid4().hex[:12]
        self.clock = clock
        self.registry = registry or registry_for(settings.resolved_tracking_uri(), Path(settings.data_dir))
        # One quick retry, no backoff: a frame must not wait seconds on a Redis that is down (redis-py's default
        # retries with exponential backoff), and after a failure Redis is left alone for REDIS_PAUSE_SECONDS.
        self.redis = redis_client if redis_client is not None else redis.Redis.from_url(
            settings.redis_url, socket_timeout=5, socket_connect_timeout=1, retry=Retry(NoBackoff(), 1))
        self._redis_paused_until = 0.0
        self._redis_failed = False  # the last Redis call failed: the next one that works retries failed mirrors
        # Every tensor operation of the sessions (steps, state (de)serialization, loading weights) runs on these
        # few threads: torch's OpenMP threads then form one team per worker instead of one per request thread, and
        # a slow session holds one worker while the others serve the rest (service.sessions.torch_thread).
        self.workers, self.threads_per_worker = session_thread_budget(settings)
        self._torch = TorchPool(self.workers, self.threads_per_worker, name="session-torch")
        # Frames are read into tensors, and histories serialized for Redis, on threads of one torch thread each (no
        # OpenMP team), not on the session threads, so both overlap the steps there (read_frame, _write_mirror).
        self._readers = TorchPool(self.workers, 1, name="session-read")
        self._sessions: dict[str, Session] = {}
        self._locks: dict[str, threading.Lock] = {}
        self._methods: dict[tuple, Method] = {}  # SessionModelSource.key -> method
        self._writers: dict[str, _MirrorWriter] = {}
        self._lock = threading.RLock()  # guards the four dicts
        # Each writer serializes the history itself, with one torch thread (no OpenMP team, no hop to another thread).
        self._mirror_pool = ThreadPoolExecutor(MIRROR_WRITERS, thread_name_prefix="session-mirror",
                                               initializer=set_own_torch_threads, initargs=(1,))
        self._methods_lock = threading.Lock()  # one method load at a time, so each version loads once
        self._create_lock = threading.Lock()  # the capacity check and the insert are one step
        self._metrics: tuple[SessionMetrics, ...] = ()  # replaced whole, so the frame path reads it without a lock

    # ------------------------------------------------------------------------------------ public

    def create(self, model: str, version: str | None = None, alias: str | None = None,
               on_gap: str = "reset", choice: dict[str, Any] | None = None,
               owner_digest: str | None = None, layout: str | dict[str, Any] = "denoiser",
               scale: int | None = None) -> Session:
        """A new session of ``model``: a registered model at ``version``, ``alias`` or (neither) its latest version,
        a pretrained model, or a method without weights at ``scale`` (service.sessions.models);
        ``choice`` (model "auto": how the version was chosen) is kept with the session's model; ``owner_digest``:
        see ``token_digest``; ``layout``: how its frames are read (``model.layouts.layout_from_value``).

        Raises UnknownModelError (KeyError) / ValueError from the registry or service.sessions.models,
        SessionLimitReached past the cap.
        """
        if on_gap not in ON_GAP_POLICIES:
            raise ValueError(f"on_gap must be one of {', '.join(ON_GAP_POLICIES)}, got {on_gap!r}")
        origin = resolve_session_model(model, self.registry, version, alias, scale)
        self._check_capacity()  # before loading weights for a session that cannot be created
        method = self._method(origin)
        with self._create_lock:
            self._check_capacity()
            now = self.clock()
            session = Session(
                id=uuid.uuid4().hex,
                model=SessionModel(name=origin.name, version=origin.version, alias=alias, method=method.name,
                                   preset=method.preset, scale=method.scale, params=method.parameter_count(),
                                   choice=choice, source=origin.source),
                on_gap=on_gap, created_at=now, last_used_at=now, ttl_seconds=self.ttl_seconds, method=method,
                owner_digest=owner_digest, layout=layout)
            with self._lock:
                self._sessions[session.id] = session
            self._mirror(session, wait=True)
        log.info("session %s created: %s", session.id, session.model.describe())
        return session

    def add_metrics(self, sink: SessionMetrics) -> None:
        """Report frames, step times and mirror failures to ``sink`` too (service.sessions.metrics)."""
        with self._lock:
            self._metrics = (*self._metrics, sink)

    def remove_metrics(self, sink: SessionMetrics) -> None:
        with self._lock:
            self._metrics = tuple(known for known in self._metrics if known is not sink)

    def count(self) -> int:
        """How many sessions are open (as the DENOISER_MAX_SESSIONS check counts them; memory alone while Redis
        is unreachable)."""
        return len(self._live_ids())

    def get(self, session_id: str) -> Session:
        """The session as it is now (without loading its state when it is not in memory); SessionNotFound."""
        return self._current(session_id, activate=False)

    def list(self) -> list[Session]:
        sessions = []
        for session_id in sorted(self._live_ids()):
            try:
                sessions.append(self.get(session_id))
            except SessionNotFound:  # expired or deleted meanwhile
                continue
        return sorted(sessions, key=lambda s: (s.created_at, s.id))

    def reset(self, session_id: str) -> Session:
        """Drop the session's history (and its established resolution); the next frame starts a new one."""
        with self._lock_for(session_id):
            self._wait_for_mirror(session_id)
            session = self._current(session_id, activate=False)
            session.state, session.next_frame_index, session.resolution = None, None, None
            session.last_used_at = self.clock()
            session.revision += 1
            with self._lock:
                self._sessions[session.id] = session  # complete now even if it was only in Redis: no history
            # Written before answering: a reset lost in a crash could let the old history meet the new stream.
            self._mirror(session, wait=True)
            return session

    def delete(self, session_id: str) -> None:
        with self._lock_for(session_id):
            self._current(session_id, activate=False)  # SessionNotFound for an unknown or expired id
            writer = self._writer_of(session_id)
            if writer is not None:
                writer.discard()  # a write landing after the delete would bring the session back
            self._forget(session_id)

            def remove(client: redis.Redis) -> None:
                pipeline = client.pipeline(transaction=True)
                pipeline.delete(self._key(session_id))
                # Another API process holding the session in memory must not write it back.
                pipeline.set(self._deleted_key(session_id), 1, ex=self.ttl_seconds)
                pipeline.execute()

            try:
                self._redis(remove)
            except redis.RedisError as error:
                log.warning("session %s: could not delete its Redis copy: %s", session_id, error)
                for sink in self._metrics:
                    sink.mirror_failed(MIRROR_DELETE)
        log.info("session %s deleted", session_id)

    def owner_digest(self, session_id: str) -> str | None:
        """The session's owner digest: from memory when it is there (no Redis access), else as ``get``."""
        return self._as_created(session_id).owner_digest

    def layout(self, session_id: str) -> str | dict[str, Any]:
        """The layout the session reads frames in: from memory when it is there (no Redis access), else as ``get``."""
        return self._as_created(session_id).layout

    def _as_created(self, session_id: str) -> Session:
        """The session for what never changes after its creation (owner digest, layout): the copy in memory when
        there is a live one, else ``get``'s."""
        with self._lock:
            session = self._sessions.get(session_id)
        if session is None or session.expired(self.clock()):
            session = self.get(session_id)
        return session

    def exists(self, session_id: str) -> bool:
        """Whether the session is live in this process's memory (no Redis access, so cheap enough to call from an
        event loop); False does not mean it does not exist: ``get`` answers that."""
        with self._lock:
            session = self._sessions.get(session_id)
        return session is not None and not session.expired(self.clock())

    def start_mirror(self, session_id: str) -> None:
        """Start writing a mirror that ``process_frame(..., start_mirror=False)`` left pending (never blocks)."""
        writer = self._writer_of(session_id)
        if writer is not None:
            writer.start()

    def read_frame(self, read: Callable[[torch.device], T]) -> T:
        """``read(device)`` on a frame-reading thread: a frame's arrays to tensors on the session device, before
        the session is touched (whatever it raises, the session is as it was)."""
        return self._readers.run(read, self.device)

    def process_frame(self, session_id: str, frame: FrameBundle | ReadFrame, *, start_mirror: bool = True,
                      frame_index_given: bool = True) -> FrameResult:
        """Run one frame through the session's method; raises SessionNotFound or FrameRejected.

        ``frame_index_given=False`` (the file had no frame index): the frame is the session's next one.

        The new revision's Redis mirror is written in the background, starting now or, with ``start_mirror=False``,
        at ``start_mirror(session_id)`` (or the session's next use, or ``flush``), whichever comes first.
        """
        self._purge_expired()
        with self._lock_for(session_id):
            # The previous frame's mirror is written while this step runs (a step never changes the state it is
            # given: tests/model/methods/test_registry.py) and must land before this frame is answered.
            self.start_mirror(session_id)
            session, planned, stepped = self._step_current(session_id, frame, frame_index_given)
            self._wait_for_mirror(session_id)  # Redis lags by one frame at most: the one being answered
            if session.superseded:  # Redis refused that mirror: another process moved the session on meanwhile
                session, planned, stepped = self._step_current(session_id, frame, frame_index_given)
                self._wait_for_mirror(session_id)
            image, state, inference_ms, sanitized = stepped
            if not sanitized.clean:
                log.warning("session %s frame %s: repaired input pixels (%s)", session_id, planned.frame.frame_index,
                            sanitized.describe())
            session.state = state
            session.next_frame_index = planned.frame.frame_index + 1
            session.frames_processed += 1
            session.resolution = planned.resolution
            session.last_used_at = self.clock()
            session.revision += 1
            self._mirror(session, wait=False, start=start_mirror)
            for sink in self._metrics:
                sink.frame_processed(session.model.name, inference_ms / 1000)
            return FrameResult(output=image, frame_index=planned.frame.frame_index, history=planned.history,
                               inference_ms=inference_ms, sanitized=sanitized, session=session)

    def _step_current(self, session_id: str, frame: FrameBundle | ReadFrame,
                      frame_index_given: bool) -> tuple[Session, _PlannedFrame, _Stepped]:
        """The frame stepped on the up-to-date session (``_current``): the session, the plan and the step's result.

        A session in memory is usually current, so its step starts at once and Redis's metadata is read while it
        runs (that read queues behind the previous frame's mirror write in Redis); if Redis says memory is behind
        (another process served the session, or it is gone), the step's result is dropped and the frame is planned
        and stepped again on what Redis holds. A frame memory would refuse waits for Redis's word first."""
        memory = self._in_memory(session_id)
        if memory is not None and memory.method is not None:
            try:
                planned = self._plan(memory, frame, frame_index_given)
            except FrameRejected:
                planned = None  # memory may be behind another process: Redis decides before a frame is refused
            if planned is not None:
                stepping = self._torch.submit(self._step, memory.method, planned.frame, planned.state)
                try:
                    session = self._current(session_id, activate=True)
                finally:
                    wait([stepping])  # no second step of this session is queued while this one runs
                if session is memory:
                    return session, planned, stepping.result()
        session = self._current(session_id, activate=True)
        if session.method is None:  # a session reset while only in Redis: memory holds no weights yet
            session.method = self._method(session.model.origin)
        planned = self._plan(session, frame, frame_index_given)
        return session, planned, self._torch.run(self._step, session.method, planned.frame, planned.state)

    def _plan(self, session: Session, frame: FrameBundle | ReadFrame, frame_index_given: bool) -> _PlannedFrame:
        """The frame rules applied to ``session`` before a step (FrameRejected if they refuse the frame)."""
        if not frame_index_given:
            frame = dataclasses.replace(frame, frame_index=session.next_frame_index or 0)
        resolution = (frame.width, frame.height)
        if session.resolution is not None and resolution != session.resolution:
            raise FrameRejected(
                f"frame {frame.frame_index} is {resolution[0]}x{resolution[1]} but this session's frames are "
                f"{session.resolution[0]}x{session.resolution[1]}; reset the session to change resolution",
                code="resolution_mismatch",
                details={"expected": list(session.resolution), "received": list(resolution)})
        history, state = self._history_for(session, frame)
        return _PlannedFrame(frame, resolution, history, state)

    def _step(self, method: Method, frame: FrameBundle | ReadFrame, state: State | None) -> _Stepped:
        """One ``method.step`` (on the torch thread): the output image (H, W, 3), the new state, the step's ms and
        what was repaired in the input first (a NaN let into the history would poison every later frame)."""
        if isinstance(frame, ReadFrame):
            batch, dtype, checked = frame.batch, getattr(torch, frame.output_dtype), frame.plainly_valid
        else:
            batch = FrameBatch.from_bundles([frame], scale=None, device=self.device)
            dtype, checked = torch.float32, False
        batch, sanitized = (batch, SanitizeReport(frames=batch.batch_size)) if checked else sanitize_frame(batch)
        with torch.inference_mode():  # faster steps than no_grad (no view or version tracking)
            start = time.perf_counter()
            output, state = method.step(batch, state)
            if output.device.type == "cuda":
                torch.cuda.synchronize(output.device)
            inference_ms = (time.perf_counter() - start) * 1000
        # A copy (the response is encoded after the lock is released, while the next frame of this session may
        # already run), kept as contiguous R, G, B planes, which the EXR encoder takes without copying.
        planes = output[0].detach().to("cpu", dtype, copy=True)
        return planes.permute(1, 2, 0).numpy(), state, inference_ms, sanitized

    def flush(self, timeout: float | None = None) -> bool:
        """Try failed mirror writes once more (unless Redis failed moments ago), then wait until every mirror
        handed to the background writers is written (or failed again); False on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._lock:
            writers = list(self._writers.values())
        if time.monotonic() >= self._redis_paused_until:
            for writer in writers:
                writer.retry()
        for writer in writers:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not writer.wait(left):
                return False
        return True

    def close(self) -> None:
        """Write pending mirrors, then drop every in-memory session and loaded method (Redis keeps the sessions
        for the next process)."""
        global _store
        if not self.flush(timeout=2 * 5 + 1):  # a write on a hung Redis gives up after its socket timeouts
            log.warning("session store closed with mirror writes still pending")
        with self._lock:
            writers = list(self._writers.values())
        for writer in writers:
            writer.close()  # no retry timer writes after the store is gone
        self._mirror_pool.shutdown(wait=False)
        self._torch.shutdown()
        self._readers.shutdown()
        with self._lock:
            self._sessions.clear()
            self._locks.clear()
            self._methods.clear()
            self._writers.clear()
        try:
            self.redis.close()
        except redis.RedisError:
            pass
        with _store_lock:
            if _store is self:
                _store = None

    # ----------------------------------------------------------------------------------- frames

    def _history_for(self, session: Session, frame: FrameBundle) -> tuple[str, State | None]:
        """Apply the frame-index rules: the X-History label and the state to give ``step``."""
        expected, index = session.next_frame_index, frame.frame_index
        if expected is None:
            return STARTED, None
        if index < expected:
            what = "repeats" if index == expected - 1 else "goes back from"
            raise FrameRejected(
                f"frame_index {index} {what} the last frame processed ({expected - 1}); this session expects "
                f"frame_index {expected} (reset the session to restart the stream)",
                code="frame_out_of_order", details={"expected": expected, "received": index})
        if index > expected:
            if session.on_gap == "reject":
                raise FrameRejected(
                    f"frame_index {index} skips {index - expected} frame(s) after {expected - 1}; this session "
                    f"(on_gap=reject) expects frame_index {expected}",
                    code="frame_gap", details={"expected": expected, "received": index})
            return RESET_GAP, None
        return (RESET_CAMERA_CUT if frame.camera_cut else CONTINUED), session.state

    # ---------------------------------------------------------------------------------- storage

    def _key(self, session_id: str) -> str:
        return f"{self.prefix}{session_id}"

    def _deleted_key(self, session_id: str) -> str:
        """Outside the sessions' key pattern, so counting sessions never reads it."""
        return f"{self.prefix.rstrip(':')}{DELETED_SUFFIX}{session_id}"

    def _tag(self, revision: int) -> str:
        return f"{self.instance}:{revision}"

    def _holds_lineage(self, session: Session, tag: str | None) -> bool:
        """Whether Redis's writer ``tag`` is one this memory copy continues: the revision it was loaded from or last
        wrote, or any revision this process wrote (a read may race this copy's writes either way: see the tag before
        a write lands and compare after, or the reverse); None: a mirror written before writer tags."""
        return tag is None or tag in (session.mirror_tag, session.origin_tag) or tag.split(":", 1)[0] == self.instance

    def _lock_for(self, session_id: str) -> threading.Lock:
        with self._lock:
            return self._locks.setdefault(session_id, threading.Lock())

    def _writer_of(self, session_id: str) -> _MirrorWriter | None:
        with self._lock:
            return self._writers.get(session_id)

    def _wait_for_mirror(self, session_id: str) -> None:
        """Until the previous frame's mirror is written, so Redis lags by one frame at most; with a mirror
        interval, Redis may lag by that long instead and the frame does not wait."""
        writer = self._writer_of(session_id)
        if writer is not None and not self.mirror_interval:
            writer.wait()

    def _forget(self, session_id: str) -> None:
        with self._lock:
            self._sessions.pop(session_id, None)
            self._locks.pop(session_id, None)
            writer = self._writers.pop(session_id, None)
            if writer is not None:
                writer.close()  # a retry landing later would bring a forgotten session back into Redis
            # Weights no session in memory uses any more are released; a session restored later reloads them.
            used = {s.model.origin.key for s in self._sessions.values()}
            for key in [key for key in self._methods if key not in used]:
                del self._methods[key]

    def _in_memory(self, session_id: str) -> Session | None:
        """The session's memory copy unless it is idle past its TTL (SessionNotFound for an id no session has)."""
        if not SESSION_ID.match(session_id):
            raise SessionNotFound(f"session {session_id!r} does not exist")
        with self._lock:
            session = self._sessions.get(session_id)
        if session is not None and session.expired(self.clock()):
            self._forget(session_id)
            return None
        return session

    def _current(self, session_id: str, activate: bool) -> Session:
        """The up-to-date session: memory, unless Redis holds a newer revision or says the session is gone.

        ``activate``: also load its state and method into memory (frames need them; views do not).
        """
        session = self._in_memory(session_id)
        now = self.clock()
        try:
            raw, raw_tag = self._redis(lambda client: client.hmget(self._key(session_id), "meta", "writer"))
        except redis.RedisError as error:
            if session is None:
                raise SessionStoreUnavailable(f"session {session_id!r} is not in memory and the session store "
                                              f"(Redis) is unreachable: {error}") from None
            log.warning("session %s: Redis unreachable, serving from memory: %s", session_id, error)
            return session
        meta = json.loads(raw) if raw is not None else None
        tag = raw_tag.decode() if raw_tag is not None else None
        if meta is None or meta["last_used_at"] + self.ttl_seconds <= now:
            if session is not None and session.mirrored_revision != session.revision and not session.superseded \
                    and not self._deleted_elsewhere(session_id):
                return session  # our last mirror failed, so Redis lacks it: memory is the record
            self._forget(session_id)
            raise SessionNotFound(f"session {session_id!r} does not exist (expired or deleted)")
        if session is not None and not session.superseded and session.revision >= meta["revision"] \
                and self._holds_lineage(session, tag):
            return session
        # Not in memory (e.g. after a restart), older than Redis or diverged from it (another API process served it).
        if not activate:
            return Session.from_metadata(meta, self.ttl_seconds, tag)
        try:
            # The whole hash in one read: the history and the metadata saying which frame it precedes match.
            fields = self._redis(lambda client: client.hgetall(self._key(session_id)))
        except redis.RedisError as error:
            raise SessionStoreUnavailable(f"session {session_id!r}: cannot read its history from Redis: {error}") \
                from None
        if b"meta" not in fields:
            self._forget(session_id)
            raise SessionNotFound(f"session {session_id!r} does not exist (expired or deleted)")
        writer_tag = fields[b"writer"].decode() if b"writer" in fields else None
        fresh = Session.from_metadata(json.loads(fields[b"meta"]), self.ttl_seconds, writer_tag)
        try:
            fresh.state = self._torch.run(state_from_fields, fields, self.device)
        except StateFormatError as error:
            raise SessionStoreUnavailable(f"session {session_id!r}: its history in Redis cannot be read ({error}); "
                                          f"reset the session to start a new one") from None
        fresh.method = self._method(fresh.model.origin)
        writer = self._writer_of(session_id)
        if writer is not None:
            writer.drop_failed()  # its retry would put an older revision over this one
        with self._lock:
            self._sessions[session_id] = fresh
        log.info("session %s restored from Redis at frame %s", session_id, fresh.next_frame_index)
        return fresh

    def _deleted_elsewhere(self, session_id: str) -> bool:
        """Whether a DELETE (here or in another API process) left its marker; False when Redis cannot say."""
        try:
            return bool(self._redis(lambda client: client.exists(self._deleted_key(session_id))))
        except redis.RedisError:
            return False

    def _redis(self, call: Callable[[redis.Redis], Any]) -> Any:
        """``call(client)``, unless Redis failed less than REDIS_PAUSE_SECONDS ago (then ConnectionError at once)."""
        if time.monotonic() < self._redis_paused_until:
            raise redis.ConnectionError("Redis failed moments ago; not retried yet")
        try:
            result = call(self.redis)
        except redis.RedisError:
            self._redis_paused_until = time.monotonic() + REDIS_PAUSE_SECONDS
            self._redis_failed = True
            raise
        if self._redis_failed:  # Redis is back: write the mirrors it missed now rather than at their timers
            self._redis_failed = False
            self._retry_failed_mirrors()
        return result

    def _retry_failed_mirrors(self) -> None:
        """Start every failed mirror write again, in the background (never blocks)."""
        with self._lock:
            writers = list(self._writers.values())
        for writer in writers:
            writer.retry()

    def _mirror_retry_delay(self) -> float:
        """Seconds until a failed mirror is tried again: once Redis is no longer left alone after its failure."""
        return max(0.0, self._redis_paused_until - time.monotonic()) + 0.05

    def _mirror(self, session: Session, wait: bool, start: bool = True) -> None:
        """Hand the session's current revision to its background writer (see the module notes); with ``wait``,
        return only once it is written (or failed)."""
        with self._lock:
            writer = self._writers.get(session.id)
            if writer is None:
                writer = self._writers[session.id] = _MirrorWriter(self._write_mirror, self._mirror_pool,
                                                                   self.mirror_interval, *self.mirror_timing,
                                                                   retry_delay=self._mirror_retry_delay)
            if session.mirror_behind_since is None:
                session.mirror_behind_since = self.clock()
        last_frame = None if session.next_frame_index is None else session.next_frame_index - 1
        writer.submit(_Snapshot(session, session.revision, json.dumps(session.metadata()), session.state,
                                last_frame, self._tag(session.revision)), start)
        if wait:
            writer.wait()

    def _write_mirror(self, snapshot: _Snapshot) -> bool:
        """Write one snapshot (metadata and state together) to Redis and restart the key's TTL; False if that
        failed (its writer retries it)."""
        session = snapshot.session
        if session.superseded:
            return True  # another process moved the session on: nothing of this copy is written any more
        key, deleted_key = self._key(session.id), self._deleted_key(session.id)
        # Beside the next frame's step, which reads the same tensors but never changes them.
        data = encode_state(snapshot.state, self.history_precision, session.codec_memo)
        mapping = {"meta": snapshot.meta, "writer": snapshot.tag, **state_fields(data, STATE_CHUNK_BYTES)}
        with self._lock:
            expected = session.mirror_tag

        def write(client: redis.Redis) -> bool:
            """Compare-and-set: False if Redis holds a revision this copy does not continue (or a delete marker)."""
            with client.pipeline(transaction=True) as pipeline:
                while True:
                    try:
                        pipeline.watch(key, deleted_key)
                        held = pipeline.hget(key, "writer")
                        if pipeline.exists(deleted_key) or (held is not None and held.decode() != expected):
                            pipeline.unwatch()
                            return False
                        pipeline.multi()
                        pipeline.delete(key)  # the previous revision's chunks go; readers see either key whole
                        pipeline.hset(key, mapping=mapping)
                        pipeline.expire(key, self.ttl_seconds)
                        pipeline.execute()
                        return True
                    except redis.WatchError:
                        continue  # the key changed between the check and the write: check again

        try:
            landed = self._redis(write)
        except redis.RedisError as error:
            log.warning("session %s: could not mirror to Redis (a restart would lose it until a retry lands): %s",
                        session.id, error)
            for sink in self._metrics:
                sink.mirror_failed(MIRROR_WRITE)
            return False
        if not landed:
            log.warning("session %s: Redis holds a history this process's copy does not continue (another API "
                        "process served the session, or deleted it); the copy is dropped", session.id)
            with self._lock:
                session.superseded = True
                if self._sessions.get(session.id) is session:
                    del self._sessions[session.id]
            return True  # nothing to retry
        with self._lock:
            session.mirror_tag = snapshot.tag
            if snapshot.revision > session.mirrored_revision:
                session.mirrored_revision, session.mirrored_frame = snapshot.revision, snapshot.frame
            if session.mirrored_revision >= session.revision:
                session.mirror_behind_since = None
        return True

    def _purge_expired(self) -> None:
        """Drop idle sessions from memory (Redis drops them by their TTL); called on every store operation that
        walks or adds sessions, so expired sessions do not hold memory for long on a busy server."""
        now = self.clock()
        with self._lock:
            expired = [sid for sid, s in self._sessions.items() if s.expired(now)]
        for session_id in expired:
            self._forget(session_id)
            log.info("session %s expired", session_id)

    def _live_ids(self, require_redis: bool = False) -> set[str]:
        """Ids of the sessions live now: in memory and not idle too long, or in Redis with metadata that says so
        (a key outlives its session's idle time by up to the time its last mirror took, and by more under a
        test's clock). ``require_redis``: SessionStoreUnavailable rather than memory alone when Redis is down."""
        self._purge_expired()
        with self._lock:
            ids = set(self._sessions)
        try:
            ids.update(self._redis(self._live_ids_in_redis))
        except redis.RedisError as error:
            if require_redis:
                raise SessionStoreUnavailable(f"the session store (Redis) is unreachable, so the open sessions "
                                              f"cannot be counted: {error}") from None
            log.warning("session store (Redis) unreachable, counting sessions in memory only: %s", error)
        return {session_id for session_id in ids if SESSION_ID.match(session_id)}

    def _live_ids_in_redis(self, client: redis.Redis) -> set[str]:
        keys = list(client.scan_iter(match=f"{self.prefix}*", count=1000))
        if not keys:
            return set()
        pipeline = client.pipeline(transaction=False)
        for key in keys:
            pipeline.hget(key, "meta")
        now = self.clock()
        live = set()
        for key, raw in zip(keys, pipeline.execute(raise_on_error=False)):
            if raw is None or isinstance(raw, redis.RedisError):
                continue  # deleted or expired since the scan, or not a hash (a delete marker of a longer prefix)
            try:
                meta = json.loads(raw)
                expired = meta["last_used_at"] + self.ttl_seconds <= now
            except (ValueError, KeyError, TypeError):
                continue  # not a session this code wrote
            if not expired:
                live.add(key.decode()[len(self.prefix):])
        return live

    def _check_capacity(self) -> None:
        # Counting memory alone while Redis is down would let every API process (and a restarted one) open up to
        # the limit each: refuse instead (503) until the count can be trusted.
        live = len(self._live_ids(require_redis=True))
        if live >= self.max_sessions:
            raise SessionLimitReached(
                f"{live} sessions are open, the server's limit is {self.max_sessions}: delete a session or wait "
                f"for an idle one to expire ({self.ttl_seconds} s)",
                details={"max_sessions": self.max_sessions, "open": live})

    def _method(self, origin: SessionModelSource) -> Method:
        """The model's method in inference form, loaded once and shared by its sessions."""
        key = origin.key
        with self._methods_lock:
            with self._lock:
                method = self._methods.get(key)
            if method is None:
                checkpoint = registered_checkpoint(origin, self.registry)  # downloads off the torch thread
                try:
                    method = self._torch.run(load_session_method, origin, checkpoint, self.device, self.forms)
                except (KeyError, ValueError) as error:  # build_method / load_checkpoint / pretrained name it
                    message = error.args[0] if isinstance(error, KeyError) and error.args else error
                    what = (f"version {origin.version} of model {origin.name!r}" if origin.source == REGISTERED
                            else f"{origin.source} {origin.name!r}")
                    raise ModelNotLoadable(f"{what} cannot be loaded: {message}",
                                           details={"model": origin.name, "version": origin.version,
                                                    "source": origin.source}) from None
                with self._lock:
                    self._methods[key] = method
                log.info("loaded %s %s (%s) for sessions", origin.source, origin.name, method.label)
            return method


def session_thread_budget(settings: Settings) -> tuple[int, int]:
    """(inference worker threads, torch threads of each): DENOISER_SESSION_WORKERS, and DENOISER_SESSION_THREADS
    or else the cores shared out among the workers."""
    threads = settings.session_threads or max(1, (os.cpu_count() or 1) // settings.session_workers)
    return settings.session_workers, threads


_store: SessionStore | None = None
_store_lock = threading.Lock()


def get_session_store() -> SessionStore:
    """The process's session store (created from the settings on first use; ``close()`` ends it)."""
    global _store
    with _store_lock:
        if _store is None:
            from core.settings import get_settings

            _store = SessionStore(get_settings())
        return _store


__all__ = ["FrameRejected", "FrameResult", "MirrorState", "ModelNotLoadable", "ReadFrame", "Session", "SessionError",
           "SessionLimitReached", "SessionModel", "SessionNotFound", "SessionStore", "SessionStoreUnavailable",
           "UnknownModelError", "get_session_store"]
