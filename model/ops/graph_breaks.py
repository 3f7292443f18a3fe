"""Calls that stay out of a ``torch.compile`` graph while the rest of a step is compiled around them.

A method's step compiled whole (``model.deployment.compiled_step``) fuses its many small image operations into few
loops; some calls gain nothing there or lose: a native library's (OIDN), a network that runs in its own inference
form, and ops whose compiled form is slower than torch's own kernel on the CPU (the bicubic ``grid_sample``, whose
decomposition gathers its 16 taps one by one). ``outside_compiled_graph`` runs such a function eagerly under
``torch.compile`` (a graph break) and as is everywhere else, ``torch.export`` included (an exported graph has no
breaks: there the function is traced like any other code).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import TypeVar

import torch

__all__ = ["outside_compiled_graph"]

F = TypeVar("F", bound=Callable)


def outside_compiled_graph(function: F) -> F:
    """``function``, run eagerly when called from code ``torch.compile`` is compiling (not exporting)."""
    eager = torch.compiler.disable(function, recursive=True)

    @functools.wraps(function)
    def call(*args, **kwargs):
        if torch.compiler.is_compiling() and not torch.compiler.is_exporting():
            return eager(*args, **kwargs)
        return function(*args, **kwargs)

    return call  # type: ignore[return-value]
