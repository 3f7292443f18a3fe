"""service.sessions.torch_thread.TorchThread: every call on one thread, results and errors passed back, no self-deadlock."""

from __future__ import annotations

import ctypes
import ctypes.util
import subprocess
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import torch

from service.sessions.torch_thread import TorchThread


def test_calls_from_many_threads_run_on_one_thread_and_return_their_results():
    worker = TorchThread()
    try:
        with ThreadPoolExecutor(4) as callers:
            results = list(callers.map(lambda i: worker.run(lambda: (threading.get_ident(), i * i)), range(12)))
        idents = {ident for ident, _ in results}
        assert len(idents) == 1 and threading.get_ident() not in idents
        assert [square for _, square in results] == [i * i for i in range(12)]
    finally:
        worker.shutdown()


def test_errors_reach_the_caller_and_the_thread_goes_on():
    worker = TorchThread()
    try:
        with pytest.raises(ValueError, match="bad frame"):
            worker.run(lambda: (_ for _ in ()).throw(ValueError("bad frame")))
        assert worker.run(lambda: 7) == 7
    finally:
        worker.shutdown()


def test_a_nested_call_runs_in_place_and_the_thread_count_is_set_there():
    worker = TorchThread(num_threads=1)
    before = torch.get_num_threads()
    try:
        outer = worker.run(lambda: (threading.get_ident(), worker.run(threading.get_ident), torch.get_num_threads()))
        assert outer[0] == outer[1] and outer[2] == 1
    finally:
        worker.shutdown()
        torch.set_num_threads(before)  # torch's setting is process-wide for threads started later


def test_after_shutdown_calls_run_in_the_caller():
    worker = TorchThread()
    worker.shutdown()
    assert worker.run(threading.get_ident) == threading.get_ident()


def test_a_pool_serves_other_calls_while_one_call_is_slow():
    from service.sessions.torch_thread import TorchPool

    pool = TorchPool(workers=2, num_threads=1)
    released = threading.Event()
    try:
        with ThreadPoolExecutor(1) as caller:
            # The slow call holds one worker until the fast one has finished (or, on one thread, gives up).
            slow = caller.submit(pool.run, lambda: released.wait(30))
            fast = pool.run(lambda: torch.get_num_threads())
            released.set()
            assert slow.result() is True  # released by the fast call, not by its timeout
        assert fast == 1
    finally:
        released.set()
        pool.shutdown()


def test_submit_lets_the_caller_work_while_the_call_runs():
    worker = TorchThread()
    started, release = threading.Event(), threading.Event()

    def held() -> int:
        started.set()
        assert release.wait(30)
        return threading.get_ident()

    try:
        future = worker.submit(held)
        assert started.wait(30) and not future.done()  # the caller is here while the call is held open
        release.set()
        assert future.result(timeout=30) != threading.get_ident()
        failing = worker.submit(lambda: (_ for _ in ()).throw(ValueError("bad frame")))
        with pytest.raises(ValueError, match="bad frame"):
            failing.result(timeout=30)
        nested = worker.run(lambda: worker.submit(threading.get_ident))  # on the worker: run in place, done
        assert nested.done() and nested.result() != threading.get_ident()
    finally:
        worker.shutdown()


ARENA_COUNT = r"""
import ctypes, ctypes.util, os, sys, tempfile, threading
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.fopen.restype = libc.malloc.restype = ctypes.c_void_p
def first_allocation():
    libc.free(ctypes.c_void_p(libc.malloc(1 << 20)))
if sys.argv[1] == "pool":
    from service.sessions.torch_thread import TorchPool
    pool = TorchPool(2)
    for _ in range(4):
        pool.run(first_allocation)
    pool.shutdown()
else:
    for _ in range(2):
        thread = threading.Thread(target=first_allocation)
        thread.start()
        thread.join()
path = os.path.join(tempfile.mkdtemp(), "malloc.xml")
stream = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, ctypes.c_void_p(stream))
libc.fclose(ctypes.c_void_p(stream))
print(open(path).read().count("<heap nr="))
"""


@pytest.mark.skipif(not hasattr(ctypes.CDLL(ctypes.util.find_library("c")), "malloc_info"), reason="not glibc")
def test_the_pools_threads_allocate_from_the_main_malloc_arena():
    # glibc's malloc_info lists one <heap> per arena: a plain thread's first allocation makes an arena of its own,
    # the pool's threads do not (model.deployment.malloc, set before they start).
    def arenas(mode: str) -> int:
        done = subprocess.run([sys.executable, "-c", ARENA_COUNT, mode], capture_output=True, text=True, check=True,
                              cwd=Path(__file__).resolve().parents[3])
        return int(done.stdout.strip())

    assert arenas("plain") >= 2
    assert arenas("pool") == 1


THREAD_COUNTS = r"""
import torch
from service.sessions.torch_thread import TorchPool
steps = TorchPool(1, 2, "steps")
steps.run(lambda: None)
readers = TorchPool(1, 1, "readers")  # started after the steps' pool, as a session's frame readers are
readers.run(lambda: None)
print(steps.run(torch.get_num_threads), readers.run(torch.get_num_threads))
"""


def test_each_pool_keeps_its_own_torch_thread_count_when_another_pool_starts_later():
    # torch applies the process's last set_num_threads to a thread when that thread first asks for its count, so
    # a steps pool whose first parallel op came after the readers started ran on the readers' one thread.
    done = subprocess.run([sys.executable, "-c", THREAD_COUNTS], capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[3])
    assert done.stdout.split() == ["2", "1"]
