"""A training job that parks at a step a test chooses, so the test can kill its worker there: a 60-step job can
finish in under a second, and waiting to catch it running would race it.

Imported into a test's worker process (``celery worker -I tests.workers.parking``), this module wraps the train
task's training (``workers.tasks.train._train_here``). With ``$PARKING_ENV`` naming a folder that holds a file
``<register_as>.park`` with a step in it, a job's first attempt writes ``<register_as>.parked`` once that step is
reported (its checkpoint is already written then) and waits there until its worker is killed (or, as in any step,
a cancel or a lost lease ends it). Later attempts and other jobs run as usual.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import workers.tasks.train as train_task

PARKING_ENV = "E2E_PARKING_DIR"


def parked_progress(context, progress, folder: str | os.PathLike | None):
    """``progress``, wrapped to park at the requested step when ``folder`` asks it for this job's first attempt."""
    name = context.params.get("register_as")
    if not folder or not name or int(context.record.get("attempts") or 1) != 1:
        return progress
    request = Path(folder) / f"{name}.park"
    if not request.is_file():
        return progress
    park_at = int(request.read_text().strip())

    def parked(current: int, total: int, message: str = "") -> None:
        progress(current, total, message)
        if current == park_at:
            # Written whole, then renamed: the test reads the step as soon as the file exists.
            marker = Path(folder) / f"{name}.parked"
            partial = marker.with_suffix(".partial")
            partial.write_text(str(current))
            partial.replace(marker)
            while True:
                context.check()
                time.sleep(0.05)

    return parked


def _parking(train_here):
    def train_with_parking(context, config, track):
        progress = parked_progress(context, context.progress, os.environ.get(PARKING_ENV))
        if progress is not context.progress:
            context.progress = progress  # this execution's context only
        return train_here(context, config, track)

    return train_with_parking


train_task._train_here = _parking(train_task._train_here)
