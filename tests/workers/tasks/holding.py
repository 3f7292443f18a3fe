"""A tiny method whose ranks hold at a chosen training step while a file asks them to, so a test can kill a node
there: a tiny training step is too quick to catch by polling.

Imported into a test's worker processes (``celery worker -I tests.workers.tasks.holding``), this module registers
``tiny_hold`` (``tiny_test``'s network); the ranks torchrun starts import it too, as every module that registered
a method outside the registry (``workers.tasks.train.plugin_modules``). With ``$E2E_HOLD_DIR`` naming a folder
that holds a file ``hold`` reading "K F" (a step and the frames per sample), a rank process about to train step
K + 1 (its checkpoint at K written) writes ``held-<pid>`` there and waits while ``hold`` exists. A rank that
resumed from step K never holds: its count of training forwards starts again at 0.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch

from model.methods.registry import MethodSpec, register
from tests.model.training_fixtures import TinyMethod

HOLD_METHOD = "tiny_hold"
HOLD_ENV = "E2E_HOLD_DIR"


class HoldingMethod(TinyMethod):
    name = HOLD_METHOD

    def step(self, frame, state):
        if self.training and torch.is_grad_enabled():  # a training forward, not a cost count or a validation
            self.training_forwards = getattr(self, "training_forwards", 0) + 1
            _hold_if_asked(self.training_forwards)
        return super().step(frame, state)


def _hold_if_asked(forward: int) -> None:
    folder = os.environ.get(HOLD_ENV)
    request = Path(folder) / "hold" if folder else None
    if request is None or not request.is_file():
        return
    step, frames_per_sample = map(int, request.read_text().split())
    if forward != step * frames_per_sample + 1:
        return
    (Path(folder) / f"held-{os.getpid()}").write_text(str(step))
    while request.is_file():
        time.sleep(0.05)


register(MethodSpec(name=HOLD_METHOD, description="test-only tiny_test network that holds at a step on request",
                    factory=HoldingMethod, presets=("default",), learned=True))
