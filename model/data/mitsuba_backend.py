"""Choosing and loading Mitsuba 3's variant: the one place that imports mitsuba.

`llvm_ad_rgb` (vectorized CPU) needs LLVM 19: Dr.Jit picks the system default LLVM otherwise, and Debian's
LLVM 15 crashes it. So the library path is set before mitsuba is first imported. `cuda_ad_rgb` is used on a
GPU; `scalar_rgb` is the slow fallback when no LLVM 19 is installed.
"""

from __future__ import annotations

import os
from pathlib import Path

LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so",
)
VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")


def find_llvm() -> str | None:
    configured = os.environ.get("DRJIT_LIBLLVM_PATH")
    if configured and Path(configured).exists():
        return configured
    return next((path for path in LLVM_CANDIDATES if Path(path).exists()), None)


def _cuda_available() -> bool:
    try:
        import torch
    except ImportError:
        return False
    return torch.cuda.is_available()


def choose_variant(requested: str | None = None) -> str:
    """The variant to render with: `requested` if given (checked), else the fastest one this machine runs."""
    if requested is not None:
        if requested not in VARIANTS:
            raise ValueError(f"unknown Mitsuba variant {requested!r}; choose one of {', '.join(VARIANTS)}")
        if requested == "cuda_ad_rgb" and not _cuda_available():
            raise ValueError("variant 'cuda_ad_rgb' needs a CUDA GPU and none is available here; use llvm_ad_rgb "
                             "(or scalar_rgb, slower)")
        if requested == "llvm_ad_rgb" and find_llvm() is None:
            raise ValueError("variant 'llvm_ad_rgb' needs libLLVM-19 (Debian package libllvm19; "
                               "scripts/setup.sh installs it) or DRJIT_LIBLLVM_PATH pointing at it")
        return requested
    if _cuda_available():
        return "cuda_ad_rgb"
    return "llvm_ad_rgb" if find_llvm() is not None else "scalar_rgb"


def load_mitsuba(variant: str | None = None):
    """Import mitsuba with `variant` active (see `choose_variant`) and return the module."""
    chosen = choose_variant(variant)
    llvm = find_llvm()
    if llvm is not None:
        os.environ.setdefault("DRJIT_LIBLLVM_PATH", llvm)
    import mitsuba as mi

    if mi.variant() != chosen:
        mi.set_variant(chosen)
    return mi
