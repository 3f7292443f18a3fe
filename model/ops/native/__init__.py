"""Hand-written CPU kernels for inference passes that torch runs as many small full-frame ones.

The fused step's learned part is some thirty float32 passes around a small network; each reads and writes whole
frames, and torch cannot fuse them on the CPU (docs/methods.md, "Native kernels"). The C sources beside this module
do several of them per pixel in one pass. Each source is compiled on first use with the machine's C compiler
(``-O3 -march=native``, OpenMP on torch's own runtime, so one thread pool) into a cache folder keyed by the source,
the flags and the CPU, and loaded with ctypes. ``usable`` says whether a call may take a source's kernels: float32
CPU tensors, no gradient, no compiler tracing, the kernels enabled (``set_enabled``) and built. Otherwise the
callers run their torch ops, which give the same values to float rounding; a failed build warns once and falls back
for good.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

import torch

__all__ = ["build", "call", "configure", "disabled", "enabled", "library", "planes", "set_enabled", "usable"]

SOURCES = Path(__file__).parent  # <name>.c, one library each, and the headers they share
# -fno-trapping-math lets floorf and comparisons vectorize (no kernel enables float traps); on x86, GCC's tuning for
# some CPUs (AMD's Zen) never emits gathers, which the warps' row loops need to vectorize
FLAGS = ["-O3", "-march=native", "-fopenmp", "-fPIC", "-shared", "-std=c11", "-fno-math-errno", "-fno-trapping-math"]
X86_FLAGS = ["-mtune-ctrl=use_gather"]
_state: dict = {"enabled": True, "cache": None}
_lock = threading.Lock()


def set_enabled(value: bool) -> None:
    """Turn the kernels on or off for this process (off: every caller runs its torch ops)."""
    _state["enabled"] = bool(value)


def configure(enabled: bool, cache: Path | None) -> None:
    """This process' switch and the folder of compiled kernels (None: the user's cache folder); the service's
    settings (``native_kernels``, ``native_cache_dir``) set both."""
    set_enabled(enabled)
    _state["cache"] = None if cache is None else Path(cache)


def enabled() -> bool:
    return _state["enabled"]


@contextlib.contextmanager
def disabled():
    """Torch's ops for every call in the block (process-wide: for one-threaded comparisons such as a benchmark's
    reference step), the previous switch after it."""
    previous = _state["enabled"]
    _state["enabled"] = False
    try:
        yield
    finally:
        _state["enabled"] = previous


def _cpu_signature() -> str:
    try:
        text = Path("/proc/cpuinfo").read_text()
        flags = next((line for line in text.splitlines() if line.startswith("flags")), "")
    except OSError:
        flags = ""
    return f"{platform.machine()} {flags}"


def _cache_dir() -> Path:
    if _state["cache"] is not None:
        return _state["cache"]
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "denoiser-service" / "native"


def build(source: str, cache: Path | None = None) -> Path:
    """Compile ``<source>.c`` into a shared library in ``cache`` (default ``_cache_dir``) unless one built from the
    same text, flags and CPU is there; its path. Raises RuntimeError when there is no compiler or it fails."""
    path = SOURCES / f"{source}.c"
    digest = hashlib.sha256(path.read_bytes())
    for header in sorted(SOURCES.glob("*.h")):  # included by some sources
        digest.update(header.read_bytes())
    flags = FLAGS + (X86_FLAGS if platform.machine().lower() in ("x86_64", "amd64") else [])
    digest.update(" ".join(flags).encode())
    digest.update(_cpu_signature().encode())
    cache = cache or _cache_dir()
    target = cache / f"{source}_{digest.hexdigest()[:16]}.so"
    if target.exists():
        return target
    compiler = os.environ.get("CC") or shutil.which("gcc") or shutil.which("cc")
    if compiler is None:
        raise RuntimeError("no C compiler (gcc or cc) on PATH")
    cache.mkdir(parents=True, exist_ok=True)
    # compiled under a temporary name, then renamed: processes building at once never load a half-written file
    handle, partial = tempfile.mkstemp(suffix=".so", dir=cache)
    os.close(handle)
    try:
        result = subprocess.run([compiler, *flags, str(path), "-o", partial, "-lm"], capture_output=True, text=True)
        if result.returncode != 0 and flags != FLAGS:  # a compiler without GCC's x86 tuning switches (clang)
            result = subprocess.run([compiler, *FLAGS, str(path), "-o", partial, "-lm"], capture_output=True,
                                    text=True)
        if result.returncode != 0:
            raise RuntimeError(f"{compiler} failed on {path.name}: {result.stderr.strip()[-2000:]}")
        os.replace(partial, target)
    finally:
        if os.path.exists(partial):
            os.unlink(partial)
    return target


@functools.cache
def library(source: str) -> ctypes.CDLL | None:
    """``<source>.c``'s kernels, built on first use; None (with one warning) where they cannot be built or loaded."""
    with _lock:
        try:
            return ctypes.CDLL(str(build(source)))
        except (RuntimeError, OSError) as error:
            warnings.warn(f"native kernels unavailable, running torch ops instead: {error}", RuntimeWarning,
                          stacklevel=2)
            return None


def usable(source: str, *tensors: torch.Tensor, dtype: torch.dtype = torch.float32) -> bool:
    """Whether a call on ``tensors`` (of ``dtype``) may run ``<source>.c``'s kernels (see the module docstring)."""
    if not _state["enabled"] or torch.is_grad_enabled():
        return False
    if torch.compiler.is_compiling() or torch.jit.is_tracing() or torch.jit.is_scripting():
        return False
    if not all(t.device.type == "cpu" and t.dtype == dtype and not t.requires_grad for t in tensors):
        return False
    return library(source) is not None


def planes(*images: torch.Tensor) -> list[torch.Tensor]:
    """The (H, W) planes of one-image tensors (1, C, H, W), channel by channel, contiguous: a kernel's array of
    pointers. The list keeps any contiguous copies alive through the call."""
    return [plane for image in images for plane in image.contiguous()[0]]


def _argument(value):
    if isinstance(value, torch.Tensor):
        return ctypes.c_void_p(value.data_ptr())
    if isinstance(value, (list, tuple)):  # planes: an array of pointers
        return (ctypes.c_void_p * max(len(value), 1))(*(t.data_ptr() for t in value))
    if value is None:
        return None
    if isinstance(value, bool):
        return ctypes.c_int64(int(value))
    if isinstance(value, int):
        return ctypes.c_int64(value)
    if isinstance(value, float):
        return ctypes.c_double(value)
    raise TypeError(f"a native kernel takes tensors, ints and floats, got {type(value).__name__}")


def call(source: str, name: str, *arguments) -> None:
    """Run ``<source>.c``'s kernel ``name`` with tensors passed by pointer (the caller makes them contiguous; a list of
    tensors as an array of pointers, None as NULL), ints as int64 and floats as double, on torch's thread count.
    Raises MemoryError where the kernel could not allocate its scratch memory (it then wrote nothing)."""
    status = getattr(library(source), name)(*map(_argument, arguments), ctypes.c_int64(torch.get_num_threads()))
    if status != 0:
        raise MemoryError(f"native kernel {name}: out of memory for its scratch buffers")
