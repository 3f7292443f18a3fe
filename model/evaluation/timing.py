"""Timing helpers shared by evaluation, benchmarks, right-sizing and the stability suite.

One way to time a method everywhere: torch's thread count set for a block (``torch_threads``), a step timed with
the device synchronized on both sides (``timed``), and the median over frames in milliseconds (``median_ms``).
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TypeVar

import torch

TIMING_FRAMES = 10
TIMING_WARMUP = 3

T = TypeVar("T")


@contextmanager
def torch_threads(threads: int | None) -> Iterator[None]:
    """Run the block with ``threads`` torch threads (None: leave torch's own), then restore the previous count."""
    previous = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work (CUDA); a no-op on the CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(call: Callable[[], T], device: torch.device) -> tuple[T, float]:
    """``call()`` and its wall time in seconds, the device synchronized before and after."""
    synchronize(device)
    start = time.perf_counter()
    result = call()
    synchronize(device)
    return result, time.perf_counter() - start


def median_ms(seconds: list[float]) -> float | None:
    """The median of ``seconds`` in milliseconds, None when there are none."""
    return 1000.0 * statistics.median(seconds) if seconds else None


def time_method(method, width: int, height: int, *, frames: int = TIMING_FRAMES, warmup: int = TIMING_WARMUP,
                device: torch.device | str = "cpu", inference_forms="measured") -> float:
    """Median ms of ``method.step`` (inference form, networks in the measured form of ``model.deployment.inference_forms``
    as sessions run them, history carried) on synthetic WxH render frames, after ``warmup`` frames, under
    ``torch.inference_mode``."""
    from model.deployment.inference_forms import load_form_table, with_inference_forms
    from model.methods.registry import example_batch

    device = torch.device(device)
    method = with_inference_forms(method.for_inference().to(device), load_form_table(inference_forms), device)
    inputs = [example_batch(height, width, seed=seed, device=device) for seed in range(min(frames + warmup, 3))]
    seconds: list[float] = []
    state = None
    with torch.inference_mode():
        for index in range(warmup + frames):
            frame = inputs[index % len(inputs)]
            (_, state), elapsed = timed(lambda: method.step(frame, state), device)
            if index >= warmup:
                seconds.append(elapsed)
    return median_ms(seconds)
