"""What the session store reports about its work, for whoever counts it (the API's /metrics, service/http/metrics.py).

The store calls these as frames are stepped and mirrors fail; it knows no metrics library. Several sinks may watch
one store (one per app built in the process: tests build several), each added with ``SessionStore.add_metrics``.
A sink must be cheap and must not raise: it runs on the frame's path.
"""

from __future__ import annotations

from typing import Protocol

# Which Redis write of a session failed (the label values of the mirror-failure count).
MIRROR_WRITE, MIRROR_DELETE = "write", "delete"


class SessionMetrics(Protocol):
    def frame_processed(self, model: str, step_seconds: float) -> None:
        """One frame stepped by a session of ``model`` (the model's name), ``step_seconds`` of ``method.step``."""

    def mirror_failed(self, operation: str) -> None:
        """A session's Redis copy could not be written (MIRROR_WRITE) or deleted (MIRROR_DELETE)."""
