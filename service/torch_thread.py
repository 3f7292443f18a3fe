"""One long-lived thread for all of the API process's torch work.

Why one thread: torch's CPU kernels parallelize with OpenMP (libgomp), and libgomp keeps a team of worker threads
for every thread that has run a parallel region. The API answers requests on a pool of threads (anyio's), so
each request thread that steps a model grows a team of its own; once the process holds more OpenMP threads than
cores, libgomp stops spinning its idle workers (throttled waits) and every small parallel region, such as the
hundreds of element-wise ops in one denoiser step, pays for waking them. Measured on the 2-core development
machine (torch 2.13): ``addcmul_`` on 3x256x256 floats takes 18 us from the only thread that runs torch and
52-66 us once a second thread has a team; a ``jnds:xs`` step at 128x128 -> 256x256 takes 21 ms on one thread
and 37-45 ms when request threads run it. Sending every tensor operation of the sessions through one thread
keeps a single team, so a step in the API costs what it costs in a script.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import torch

T = TypeVar("T")


class TorchThread:
    """Runs callables one at a time on its own thread (``run`` blocks the caller until done and returns or
    raises what the callable did). ``num_threads`` sets torch's intra-op thread count on that thread."""

    def __init__(self, num_threads: int | None = None, name: str = "torch") -> None:
        self._ident: int | None = None
        self._executor = ThreadPoolExecutor(1, thread_name_prefix=name, initializer=self._start,
                                            initargs=(num_threads,))

    def _start(self, num_threads: int | None) -> None:
        self._ident = threading.get_ident()
        if num_threads:
            torch.set_num_threads(num_threads)

    def run(self, function: Callable[..., T], *args, **kwargs) -> T:
        if threading.get_ident() == self._ident:  # already on it: a nested call must not wait for itself
            return function(*args, **kwargs)
        try:
            future = self._executor.submit(function, *args, **kwargs)
        except RuntimeError:  # shut down (the store is closing): run here rather than fail a last write
            return function(*args, **kwargs)
        return future.result()

    def shutdown(self) -> None:
        self._executor.shutdown(wait=True)
