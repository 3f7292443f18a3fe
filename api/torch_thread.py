"""A few long-lived threads for all of the API process's torch work, each with its own torch thread count.

Why dedicated threads: torch's CPU kernels parallelize with OpenMP (libgomp), and libgomp keeps a team of worker
threads for every thread that has run a parallel region. The API answers requests on a pool of threads (anyio's),
so each request thread that steps a model grows a team of its own; once the process holds more OpenMP threads
than cores, libgomp stops spinning its idle workers (throttled waits) and every small parallel region, such as
the hundreds of element-wise ops in one denoiser step, pays for waking them. Measured on the 2-core development
machine (torch 2.13): ``addcmul_`` on 3x256x256 floats takes 18 us from the only thread that runs torch and
52-66 us once a second thread has a team; a ``jnds:xs`` step at 128x128 -> 256x256 takes 21 ms on one thread
and 37-45 ms when request threads run it. Sending every tensor operation of the sessions through a fixed set of
``workers`` threads of ``num_threads`` torch threads each keeps the process at ``workers x num_threads`` OpenMP
threads, a budget the deployment chooses (DENOISER_SESSION_WORKERS, DENOISER_SESSION_THREADS).

Why more than one: with a single thread one slow frame (a large resolution, a large model) stalls every other
session's frame queued behind it. Calls are taken first come, first served by whichever worker is free, and a
session has at most one step queued at a time (its frames are serialized), so a slow session holds one worker
and the others keep serving the rest.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

import torch

T = TypeVar("T")


class TorchPool:
    """Runs callables on ``workers`` threads of its own (``run`` blocks the caller until done and returns or raises
    what the callable did). ``num_threads`` sets torch's intra-op thread count on each of them (an OpenMP
    setting of the calling thread, so each worker keeps its own)."""

    def __init__(self, workers: int = 1, num_threads: int | None = None, name: str = "torch") -> None:
        self.workers = workers
        self.num_threads = num_threads
        self._idents: set[int] = set()
        share_one_malloc_arena()  # before the workers' first allocation picks their arena
        self._executor = ThreadPoolExecutor(workers, thread_name_prefix=name, initializer=self._start,
                                            initargs=(num_threads,))

    def _start(self, num_threads: int | None) -> None:
        self._idents.add(threading.get_ident())
        if num_threads:
            torch.set_num_threads(num_threads)

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


_M_ARENA_MAX = -8  # glibc's malloc.h


def share_one_malloc_arena() -> bool:
    """Make threads that allocate for the first time from now on use glibc's main malloc arena; False off glibc.

    Why: glibc gives a new thread an arena of its own, whose heaps are at most 64 MB and shrink as blocks are
    freed, so the tens of megabytes of tensors a large frame's step allocates fault their pages in again every
    step. Measured on the 2-core development machine: a `wskpn:s` step at 1920x1080 took 1.95-2.06 s (median of 5)
    on a thread of its own against 1.26-1.51 s on the main thread (3.5x the page faults, 4x the kernel time), and
    1.47 s on a thread sharing the main arena. The sessions' steps all run on this module's threads.
    """
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc (macOS has no mallopt)
        return False
    return bool(mallopt(_M_ARENA_MAX, 1))


def _called_here(function: Callable[..., T], *args, **kwargs) -> Future[T]:
    """``function`` run on the calling thread, as a done future."""
    future: Future[T] = Future()
    try:
        future.set_result(function(*args, **kwargs))
    except BaseException as error:  # handed to whoever reads the future, as the executor would
        future.set_exception(error)
    return future
