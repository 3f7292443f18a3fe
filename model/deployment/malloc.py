"""glibc's malloc set for the large, short-lived tensors of full-resolution frames.

A step at 1920x1080 allocates and frees hundreds of tensors of tens to hundreds of megabytes. Left at its defaults,
glibc hands out every block over its mmap threshold (32 MB at most) as fresh pages from the kernel and gives them
back when the block is freed, and returns freed memory at the top of the heap past a trim threshold of 128 kB, so
every step faults all of its tensors' pages in again. Measured on the 2-core development machine, the shipped
`fused-balanced-x1` at 1920x1080 on 2 torch threads (medians of 5 steps, one process each): 2.85 s a step with
2.9 M page faults and 9.1 s of kernel time, against 1.85 s with 0.75 M faults and 3.0 s once large blocks come from
the heap and the heap keeps up to ``TRIM_THRESHOLD_BYTES`` of freed memory (a 256 MB threshold kept half of the
faults). The price: the process keeps up to that much freed memory instead of returning it.

Threads get arenas of their own, too: each new thread allocates from an arena whose heaps are at most 64 MB and
shrink as blocks are freed, which costs the same faults (a `wskpn:s` step at 1920x1080: 1.95-2.06 s on a thread
of its own, 1.26-1.51 s on the main thread, 1.47 s on a thread sharing the main arena).

Processes that step frames call ``tune_for_large_frames`` before they allocate them: the API's session threads
(service.sessions.torch_thread) and the ``denoiser`` command line. Everything here is a no-op returning False off glibc.
"""

from __future__ import annotations

import ctypes
import ctypes.util

# glibc's malloc.h
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_M_ARENA_MAX = -8

TRIM_THRESHOLD_BYTES = 1 << 30


def _mallopt():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc (macOS has no mallopt)
        return None


def share_one_malloc_arena() -> bool:
    """Threads that allocate for the first time from now on use glibc's main arena (see the module notes)."""
    mallopt = _mallopt()
    return mallopt is not None and bool(mallopt(_M_ARENA_MAX, 1))


def keep_large_blocks_in_the_heap(trim_threshold: int = TRIM_THRESHOLD_BYTES) -> bool:
    """Large blocks come from the heap instead of mmap, and the heap returns freed memory to the system only past
    ``trim_threshold`` bytes, so the next step reuses the pages the last one freed (see the module notes)."""
    mallopt = _mallopt()
    return mallopt is not None and bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_threshold))


def release_freed_memory() -> bool:
    """Give the heap's freed pages back to the system now (glibc's malloc_trim), e.g. after a decode that was
    refused or failed: the trim threshold above would otherwise keep them for good."""
    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return False
    return bool(trim(0))


def tune_for_large_frames() -> bool:
    """Both of the above; True where both took effect."""
    return share_one_malloc_arena() and keep_large_blocks_in_the_heap()
