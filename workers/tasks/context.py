"""What a running job sees: its record and folders, progress reporting, cancellation, its log, its lease.

``JobContext.progress(current, total, message)`` is the one progress call of every job kind. It computes the ETA,
mirrors ``{current, total, message, eta_seconds}`` into the job record and Celery's result backend (at most
every ``PROGRESS_INTERVAL`` seconds, and always for the first and the last step), logs now and then, and raises
``JobCancelled`` once a cancel was requested, which is how single-process work stops cooperatively (training's
progress callback may raise; the last checkpoint stays).

A ``Watchdog`` thread keeps the execution's lease alive (the heartbeat) and watches the cancel flag, so a cancel
is seen within a second even while the job sits in a long step, and callbacks registered with ``on_cancel``
(stopping DDP ranks) run from it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from core.settings import Settings
from core.storage import Storage
from core.job_store import JobStore
from workers.redis_retry import with_retry

PROGRESS_INTERVAL = 0.5  # seconds between progress writes to Redis
LOG_INTERVAL = 10.0  # seconds between progress lines in the job log
HEARTBEAT_INTERVAL = 5.0  # seconds between lease refreshes (the lease lives LEASE_TTL_SECONDS)
WATCH_INTERVAL = 0.5  # seconds between looks at the cancel flag

log = logging.getLogger("denoiser.jobs")


class JobCancelled(Exception):
    """Raised inside a job when its cancel flag is set; the job ends in state ``cancelled``."""


class LeaseLost(Exception):
    """This execution's lease passed to another one (it was presumed dead): stop without touching the record."""


class JobFailure(Exception):
    """A job failed for a reason that is the input's, not a bug: ends the job with this code and message."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code
        self.message = message


ProgressSink = Callable[[dict[str, Any]], None]  # Celery's update_state, or nothing in tests


@dataclass
class JobContext:
    record: dict[str, Any]
    store: JobStore
    storage: Storage
    settings: Settings
    owner: str
    sink: ProgressSink | None = None
    cancelled: threading.Event = field(default_factory=threading.Event)
    lease_lost: threading.Event = field(default_factory=threading.Event)
    sleep: Callable[[float], None] = time.sleep  # between Redis retries (tests pass one that does not wait)

    def __post_init__(self) -> None:
        self.started = time.monotonic()
        self.baseline = 0  # progress already made when this execution started (a resumed training's step)
        self._last_write = 0.0
        self._last_log = 0.0
        self._cancel_callbacks: list[Callable[[], None]] = []
        self._callback_lock = threading.Lock()
        self.logger = log.getChild(self.job_id[:8])

    @property
    def job_id(self) -> str:
        return self.record["id"]

    @property
    def params(self) -> dict[str, Any]:
        return self.record["params"]

    @property
    def folder(self) -> Path:
        path = self.storage.job(self.job_id)
        path.mkdir(parents=True, exist_ok=True)
        return path

    @property
    def torch_device(self) -> str:
        return "cuda" if self.record["device"] == "gpu" else "cpu"

    # ---------------------------------------------------------------------------------- progress

    def progress(self, current: int, total: int, message: str = "") -> None:
        self.check()
        now = time.monotonic()
        first = self._last_write == 0.0
        if first or current >= total or now - self._last_write >= PROGRESS_INTERVAL:
            self._last_write = now
            report = {"current": int(current), "total": int(total), "message": message,
                      "eta_seconds": self.eta(current, total, now)}
            # A Redis blip must not end the attempt: retried with backoff for settings.redis_retry_seconds.
            self._retried(lambda: self.store.set_progress(self.job_id, report), "progress")
            if self.sink is not None:
                self._retried(lambda: self.sink(report), "progress to Celery")
            if first or current >= total or now - self._last_log >= LOG_INTERVAL:
                self._last_log = now
                eta = "" if report["eta_seconds"] is None else f", ETA {report['eta_seconds']:.0f} s"
                self.logger.info("progress %d/%d%s: %s", current, total, eta, message)
        self.check()

    def _retried(self, call: Callable[[], Any], what: str) -> Any:
        return with_retry(call, self.settings.redis_retry_seconds, f"job {self.job_id[:8]} {what}",
                          sleep=self.sleep)

    def eta(self, current: int, total: int, now: float | None = None) -> float | None:
        """Seconds left at the rate this execution has made progress so far (None until it has made some)."""
        done = current - self.baseline
        if done <= 0 or total <= 0:
            return None
        elapsed = (now if now is not None else time.monotonic()) - self.started
        return round(max(0.0, elapsed / done * (total - current)), 1)

    # ------------------------------------------------------------------------------ cancellation

    def check(self) -> None:
        if self.lease_lost.is_set():
            raise LeaseLost(f"job {self.job_id}: another execution took over its lease")
        if self.cancelled.is_set():
            raise JobCancelled(f"job {self.job_id} was cancelled")

    def on_cancel(self, callback: Callable[[], None]) -> Callable[[], None]:
        """Run ``callback`` (from the watchdog thread) when a cancel arrives; returns a function that unregisters it."""
        with self._callback_lock:
            self._cancel_callbacks.append(callback)
            run_now = self.cancelled.is_set()
        if run_now:
            callback()

        def unregister() -> None:
            with self._callback_lock:
                if callback in self._cancel_callbacks:
                    self._cancel_callbacks.remove(callback)

        return unregister

    def _fire_cancel(self) -> None:
        with self._callback_lock:
            callbacks = list(self._cancel_callbacks)
        for callback in callbacks:
            try:
                callback()
            except Exception:  # a failing stop must not kill the watchdog (the lease would lapse)
                self.logger.exception("cancel callback failed")

    # ------------------------------------------------------------------------------------ MLflow

    def set_mlflow_run(self, run_id: str | None, experiment_id: str | None = None) -> None:
        if not run_id:
            return
        self.store.update(self.job_id, mlflow_run_id=run_id, mlflow_url=mlflow_url(self.settings, run_id,
                                                                                   experiment_id))

    @contextmanager
    def ending(self, tracker) -> Iterator[None]:
        """Ends ``tracker``'s MLflow run (None: nothing to end) as the block ends: FINISHED, or KILLED on a cancel,
        FAILED on any other error."""
        try:
            yield
        except BaseException:
            if tracker is not None:
                tracker.finish("KILLED" if self.cancelled.is_set() else "FAILED")
            raise
        if tracker is not None:
            tracker.finish("FINISHED")


def mlflow_url(settings: Settings, run_id: str, experiment_id: str | None = None) -> str | None:
    """A link to the run in the MLflow UI (settings.mlflow_ui_url), or None when no UI is configured."""
    if not settings.mlflow_ui_url:
        return None
    base = settings.mlflow_ui_url.rstrip("/")
    if experiment_id is None:
        experiment_id = _experiment_of(settings, run_id)
    if experiment_id is None:
        return f"{base}/#/runs/{run_id}"
    return f"{base}/#/experiments/{experiment_id}/runs/{run_id}"


def _experiment_of(settings: Settings, run_id: str) -> str | None:
    try:
        from core.tracking import MLflowTracker

        return MLflowTracker(settings.resolved_tracking_uri()).client.get_run(run_id).info.experiment_id
    except Exception:  # only a link is at stake
        return None


class Watchdog:
    """Background thread of one execution: refreshes its lease, notices cancel requests (``with`` block)."""

    def __init__(self, context: JobContext, heartbeat_interval: float = HEARTBEAT_INTERVAL,
                 watch_interval: float = WATCH_INTERVAL) -> None:
        self.context = context
        self.heartbeat_interval = heartbeat_interval
        self.watch_interval = watch_interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"job-{context.job_id[:8]}-watchdog", daemon=True)

    def __enter__(self) -> Watchdog:
        self._thread.start()
        return self

    def __exit__(self, *exc_info) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    def _run(self) -> None:
        context = self.context
        last_beat = time.monotonic()
        while not self._stop.wait(self.watch_interval):
            try:
                if time.monotonic() - last_beat >= self.heartbeat_interval:
                    last_beat = time.monotonic()
                    if not context.store.heartbeat(context.job_id, context.owner):
                        context.lease_lost.set()
                        context.logger.error("lease taken over by another execution; stopping")
                        context._fire_cancel()
                if not context.cancelled.is_set() and context.store.cancel_requested(context.job_id):
                    context.cancelled.set()
                    context.logger.info("cancel requested")
                    context._fire_cancel()
            except Exception:  # Redis briefly unreachable: try again on the next tick
                context.logger.warning("watchdog could not reach Redis", exc_info=True)


class JobLogHandler(logging.FileHandler):
    """Everything logged while the job runs, by any logger, into storage.job(id)/job.log."""

    def __init__(self, path: Path) -> None:
        super().__init__(path, encoding="utf-8")
        self.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))


