"""The Celery task that runs every job, the execution around each kind, and recovery when a worker starts.

``run_job(job_id)`` takes only the id (the record in Redis has the rest, ``core.job_store``). An execution:

1. takes the job's lease (``JobStore.start``); a job that finished, was cancelled while queued, is unknown or
   is being run by another live execution is not run again: the task returns at once (duplicate deliveries);
2. runs the kind's ``run(context)`` with a watchdog thread refreshing the lease every few seconds and watching
   the cancel flag, and a log handler writing everything logged to ``jobs/<id>/job.log``;
3. ends the record in ``succeeded`` (with the result), ``cancelled`` or ``failed`` (with an error code and
   message), and releases the lease. An execution that lost its lease to another one leaves the record alone.

Progress goes to the record and to Celery's result backend (``update_state`` with state ``PROGRESS`` and meta
``{current, total, message, eta_seconds}``). Acks are late (``core.celery_app``), and on ``worker_ready``
every worker starts a thread that recovers orphaned jobs now and every minute (``workers.tasks.recovery``).
"""

from __future__ import annotations

import logging
import socket
import threading
from typing import Any

from celery import Celery
from celery.signals import worker_ready, worker_shutdown

from core.errors import DomainError
from core.heartbeats import Heartbeat
from core.jobs.dispatch import TASK_NAME, CeleryDispatcher
from core.jobs.files import LOG_FILE
from core.names import QUEUES
from core.settings import Settings, get_settings
from core.storage import Storage, get_storage
from core.celery_app import app
from core.job_store import JobStore, execution_owner, get_job_store
from workers.tasks.context import (
    JobCancelled,
    JobContext,
    JobFailure,
    JobLogHandler,
    LeaseLost,
    ProgressSink,
    Watchdog,
)
from workers.tasks.kinds import module_for
from workers.tasks.recovery import RECOVERY_INTERVAL, recover_orphaned_jobs, waiting_task_ids

log = logging.getLogger("denoiser.jobs")
# The job log wants the INFO lines of this project's loggers whatever level the worker's root logger has.
logging.getLogger("denoiser").setLevel(logging.INFO)


@app.task(bind=True, name=TASK_NAME, acks_late=True, reject_on_worker_lost=True)
def run_job(self, job_id: str) -> dict[str, Any]:
    def sink(report: dict[str, Any]) -> None:
        self.update_state(state="PROGRESS", meta=report)

    return execute(job_id, get_job_store(), get_storage(), get_settings(), sink if self.request.id else None)


def execute(job_id: str, store: JobStore, storage: Storage, settings: Settings,
            sink: ProgressSink | None = None) -> dict[str, Any]:
    """Run one job to its end (see the module notes); returns a short summary for Celery's result."""
    owner = execution_owner()
    decision = store.start(job_id, owner)
    if not decision.started:
        log.info("job %s not run: %s", job_id, decision.outcome)
        state = decision.record["state"] if decision.record else None
        return {"job_id": job_id, "state": state, "skipped": decision.outcome}
    context = JobContext(decision.record, store, storage, settings, owner, sink)
    apply_job_threads(settings)
    handler = JobLogHandler(context.folder / LOG_FILE)
    root = logging.getLogger()
    root.addHandler(handler)
    if _heartbeat is not None:
        _heartbeat.job = job_id
    try:
        return _run(context)
    finally:
        if _heartbeat is not None:
            _heartbeat.job = None
        root.removeHandler(handler)
        handler.close()
        store.release(job_id, owner)


def apply_job_threads(settings: Settings) -> None:
    """The job's torch thread budget (DENOISER_JOB_THREADS): a worker beside an API serving sessions must not take
    every core (DDP ranks share the budget, see workers.tasks.train)."""
    if settings.job_threads:
        import torch

        torch.set_num_threads(settings.job_threads)


def _run(context: JobContext) -> dict[str, Any]:
    store, job_id, record = context.store, context.job_id, context.record
    logger = context.logger
    try:
        with Watchdog(context):
            logger.info("attempt %d of %s job %s started on %s (queue %s)", record["attempts"], record["kind"],
                        job_id, socket.gethostname(), record["queue"])
            context.check()
            result = module_for(record["kind"]).run(context)
    except LeaseLost:
        logger.error("another execution owns this job now; this one stops without changing its record")
        return {"job_id": job_id, "state": None, "skipped": "lease_lost"}
    except JobCancelled:
        logger.info("cancelled")
        final = store.finish(job_id, "cancelled")
    except (JobFailure, DomainError) as error:  # the input's fault, found only now (e.g. a dataset deleted since)
        logger.error("failed: %s", error.message)
        final = store.finish(job_id, "failed", error={"code": error.code, "message": error.message})
    except Exception as error:
        logger.exception("failed")
        final = store.finish(job_id, "failed", error={"code": _error_code(error),
                                                      "message": f"{type(error).__name__}: {error}"})
    else:
        progress = dict(store.require(job_id)["progress"])
        if progress["total"]:
            progress.update(current=progress["total"], eta_seconds=0.0)
        final = store.finish(job_id, "succeeded", result=result, progress=progress)
        logger.info("succeeded")
    state = final["state"] if final else None
    return {"job_id": job_id, "state": state}


def _error_code(error: Exception) -> str:
    from model.io.frames import FrameError
    from workers.ddp import RankError

    if isinstance(error, RankError):
        return "ranks_failed"
    if isinstance(error, (ValueError, KeyError, FileNotFoundError, FileExistsError, FrameError)):
        return "invalid_input"  # e.g. the dataset changed between submission and run
    return "internal_error"


# ------------------------------------------------------------------------------------------ recovery

def recover_now(celery: Celery = app, store: JobStore | None = None) -> None:
    store = store or get_job_store()
    dispatcher = CeleryDispatcher(celery)
    report = recover_orphaned_jobs(store, dispatcher.send, waiting_task_ids(store.redis, QUEUES))
    if report.resent or report.failed or report.cancelled:
        log.warning("recovery: resent %s, failed %s, cancelled %s", report.resent, report.failed, report.cancelled)


def _recovery_loop(stop: threading.Event) -> None:
    while True:
        try:
            recover_now()
        except Exception:  # Redis down for a moment: the next round tries again
            log.exception("job recovery failed")
        if stop.wait(RECOVERY_INTERVAL):
            return


_recovery_stop = threading.Event()


@worker_ready.connect
def _start_recovery(**_: Any) -> None:
    threading.Thread(target=_recovery_loop, args=(_recovery_stop,), name="job-recovery", daemon=True).start()


# ------------------------------------------------------------------------------------------ heartbeat

_heartbeat: Heartbeat | None = None


@worker_ready.connect
def _start_heartbeat(sender: Any = None, **_: Any) -> None:
    """The worker's liveness for the API (core.heartbeats): a thread, so a long job does not silence it."""
    global _heartbeat
    hostname = getattr(sender, "hostname", None) or f"celery@{socket.gethostname()}"
    _heartbeat = Heartbeat(get_job_store().redis, hostname, _consumed_queues(sender),
                           get_settings().worker_heartbeat_seconds).start()


def _consumed_queues(consumer: Any) -> list[str]:
    try:
        return sorted(consumer.app.amqp.queues.consume_from)
    except AttributeError:  # not a worker's consumer (e.g. a test): the queues this app knows
        return list(QUEUES)


@worker_shutdown.connect
def _stop_heartbeat(**_: Any) -> None:
    if _heartbeat is not None:
        _heartbeat.stop()
