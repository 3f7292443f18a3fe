"""The native kernels serve inference: their tests run without gradients unless a test turns them on."""

import pytest
import torch


@pytest.fixture(autouse=True)
def _no_grad():
    with torch.no_grad():
        yield
