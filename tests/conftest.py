"""Suite-wide test settings."""

from __future__ import annotations

import os
import random
import tempfile

import numpy as np
import pytest
import torch


@pytest.fixture(autouse=True)
def single_torch_thread():
    """Run each test's torch work on one thread.

    The tests use tiny tensors: OpenMP's thread start-up and spinning dominate them, and on a loaded 2-core
    machine two threads made a 16x16 step take over 100x longer than one. Tests that time or
    parallelize things set their own thread counts.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(autouse=True)
def seeded_random():
    """Seed torch, NumPy and ``random`` before each test, so a test's draws do not depend on the tests before it."""
    torch.manual_seed(0)
    np.random.seed(0)
    random.seed(0)


# One folder of compiled native kernels for the whole run, whatever data folder a test's settings name: compiled
# once (about a second per source), not once per test (model/ops/native).
os.environ.setdefault("DENOISER_NATIVE_CACHE_DIR", os.path.join(tempfile.gettempdir(), "denoiser-test-native-kernels"))
