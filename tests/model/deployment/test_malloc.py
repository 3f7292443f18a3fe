"""model.deployment.malloc: glibc's allocator keeps large blocks in its heap once tuned (checked in fresh processes)."""

from __future__ import annotations

import ctypes
import ctypes.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

# Holds a 64 MB block (over glibc's largest mmap threshold) and one freed 512 MB block, then prints glibc's own
# account (malloc_info): how much is in mmapped blocks, and how much memory the heap holds from the system.
MALLOC_STATE = r"""
import ctypes, ctypes.util, os, sys, tempfile
libc = ctypes.CDLL(ctypes.util.find_library("c"))
libc.fopen.restype = libc.malloc.restype = ctypes.c_void_p
if sys.argv[1] == "tuned":
    from model.deployment.malloc import tune_for_large_frames
    assert tune_for_large_frames()
held = libc.malloc(64 << 20)
libc.free(ctypes.c_void_p(libc.malloc(512 << 20)))
path = os.path.join(tempfile.mkdtemp(), "malloc.xml")
stream = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, ctypes.c_void_p(stream))
libc.fclose(ctypes.c_void_p(stream))
print(open(path).read())
"""


def malloc_state(mode: str) -> tuple[int, int]:
    """(bytes in mmapped blocks, bytes the heap holds from the system) in a process run as ``mode``: the totals
    malloc_info ends with (the interpreter maps a few small blocks of its own before anything is tuned)."""
    done = subprocess.run([sys.executable, "-c", MALLOC_STATE, mode], capture_output=True, text=True, check=True,
                          cwd=Path(__file__).resolve().parents[3])
    mmapped = int(re.findall(r'<total type="mmap" count="\d+" size="(\d+)"', done.stdout)[-1])
    system = int(re.findall(r'<system type="current" size="(\d+)"', done.stdout)[-1])
    return mmapped, system


@pytest.mark.skipif(not hasattr(ctypes.CDLL(ctypes.util.find_library("c")), "malloc_info"), reason="not glibc")
def test_large_blocks_come_from_the_heap_and_freed_ones_stay_there_once_tuned():
    mmapped, system = malloc_state("default")
    assert mmapped >= 64 << 20  # the 64 MB block is mapped; the freed 512 MB one was unmapped
    assert system < 64 << 20
    mmapped, system = malloc_state("tuned")
    assert mmapped < 64 << 20
    assert system >= (64 + 512) << 20  # the freed block's pages stay for the next step (under the 1 GB threshold)
