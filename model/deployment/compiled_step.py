"""A method's whole ``step`` compiled by ``torch.compile``, with the eager step as its fallback.

A recurrent step like the fused family's is dozens of small image operations around its network (warps, the
history tests, the rectification, the feature assembly, the blend), each a full pass over the frame, on the CPU
one parallel region each. Compiled whole (inductor, C++ through the system compiler), they run as a few fused loops.
What gains nothing there stays out of the graph (``model.ops.graph_breaks``): OIDN, the networks (each runs in the
inference form its table row names) and the bicubic warp.

One ``CompiledStep`` per loaded method. The first frame at a resolution compiles (torch's default shape policy:
static shapes first, one dynamic recompile when a second resolution comes, then no more; see docs/methods.md,
"Fast forms of the fused step"). Where compiling fails (no C++ compiler, an inductor error) the step warns once and
runs eagerly from then on, with the same results.
"""

from __future__ import annotations

import logging
import subprocess
import threading
from collections.abc import Callable
from typing import Any

import torch

__all__ = ["CompiledStep", "COMPILE_BACKEND", "COMPILE_ERRORS"]

log = logging.getLogger(__name__)

COMPILE_BACKEND: str | Callable = "inductor"  # read at each compilation (tests put a failing backend here)

# What a failed compilation raises: dynamo's errors (a backend failure among them), inductor's own, and a missing
# or failing compiler process. An error of the step itself (a bad frame) is raised by the code dynamo runs, as is.
COMPILE_ERRORS: tuple[type[BaseException], ...] = (
    torch._dynamo.exc.TorchDynamoException, torch._inductor.exc.InductorError, torch._inductor.exc.CppCompileError,
    subprocess.CalledProcessError, FileNotFoundError)


class CompiledStep:
    """``step(frame, state)`` compiled on first use; eager for good once a compilation has failed."""

    def __init__(self, step: Callable[[Any, Any], Any], backend: str | Callable | None = None) -> None:
        self.step = step
        self.backend = backend  # None: COMPILE_BACKEND
        self.compiled: Callable[[Any, Any], Any] | None = None
        self.failure: str | None = None
        self._lock = threading.Lock()

    def __call__(self, frame: Any, state: Any) -> Any:
        if self.failure is None:
            with self._lock:
                if self.compiled is None:
                    self.compiled = torch.compile(self.step, backend=self.backend or COMPILE_BACKEND)
            try:
                return self.compiled(frame, state)
            except COMPILE_ERRORS as error:
                self.failure = f"{type(error).__name__}: {' '.join(str(error).split())[:400]}"
                log.warning("compiling the step failed (%s); it runs eagerly from now on", self.failure)
        return self.step(frame, state)
