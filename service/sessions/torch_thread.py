"""A few long-lived threads for all of the API process's torch work, each with its own torch thread count.

Why dedicated threads: torch's CPU kernels parallelize with OpenMP (libgomp), and libgomp keeps a team of worker
threads for every thread that has run a parallel region. The API answers requests on a pool of threads (anyio's),
so each request thread that steps a model grows a team of its own; once the process holds more OpenMP threads
than cores, libgomp stops spinning its idle workers (throttled waits) and every small parallel region, such as
the hundreds of element-wise ops in one denoiser step, pays for waking them, and a step run from request threads
is much slower than the same step on one thread. Sending every tensor operation of the sessions through a fixed set
of ``workers`` threads of ``num_threads`` torch threads each keeps the process at ``workers x num_threads`` OpenMP
threads, a budget the deployment chooses (DENOISER_SESSION_WORKERS, DENOISER_SESSION_THREADS).

Why more than one: with a single thread one slow frame (a large resolution, a large model) stalls every other
session's frame queued behind it. Calls are taken first come, first served by whichever worker is free, and a
session has at most one step queued at a time (its frames are serialized), so a slow session holds one worker
and the others keep serving the rest.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

import torch

from model.deployment.malloc import tune_for_large_frames

T = TypeVar("T")


class TorchPool:
    """Runs callables on ``workers`` threads of its own (``run`` blocks the caller until done and returns or raises
    what the callable did). ``num_threads`` sets torch's intra-op thread count on each of them (an OpenMP
    setting of the calling thread, so each worker keeps its own)."""

    def __init__(self, workers: int = 1, num_threads: int | None = None, name: str = "torch") -> None:
        self.workers = workers
        self.num_threads = num_threads
        self._idents: set[int] = set()
        tune_for_large_frames()  # before the workers' first allocation picks their arena
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix=name, initializer=self._start,
                                            initargs=(num_threads,))

    def _start(self, num_threads: int | None) -> None:
        self._idents.add(threading.get_ident())
        if num_threads:
            set_own_torch_threads(num_threads)

    def run(self, function: Callable[..., T], *args, **kwargs) -> T:
        return self.submit(function, *args, **kwargs).result()

    def submit(self, function: Callable[..., T], *args, **kwargs) -> Future[T]:
        """``function(*args, **kwargs)`` started on a worker; its future (the caller may work meanwhile)."""
        if threading.get_ident() in self._idents:  # already on one: a nested call must not wait for a free worker
            return _called_here(function, *args, **kwargs)
        try:
            return self._executor.submit(function, *args, **kwargs)
        except RuntimeError:  # shut down (the store is closing): run here rather than fail a last write
            return _called_here(function, *args, **kwargs)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=True)


class TorchThread(TorchPool):
    """A pool of one: every call on the same thread."""

    def __init__(self, num_threads: int | None = None, name: str = "torch") -> None:
        super().__init__(1, num_threads, name)


def set_own_torch_threads(num_threads: int) -> None:
    """The calling thread's torch thread count, kept whatever other threads set later.

    torch applies the process's last ``set_num_threads``, whichever thread made it, to a thread the first time
    that thread asks for its count (its first parallel op does), so a session thread of 2 whose first step came
    after a frame reader of 1 started stepped on one thread. Asking first ends that first time here."""
    torch.get_num_threads()
    torch.set_num_threads(num_threads)


def _called_here(function: Callable[..., T], *args, **kwargs) -> Future[T]:
    """``function`` run on the calling thread, as a done future."""
    future: Future[T] = Future()
    try:
        future.set_result(function(*args, **kwargs))
    except BaseException as error:  # handed to whoever reads the future, as the executor would
        future.set_exception(error)
    return future
