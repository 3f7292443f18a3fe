"""Domain errors: what went wrong, named for what it is, without HTTP.

Job checks, the registry and the worker raise these; the API turns each class into its status code in one
place (``service.http.errors.ERROR_STATUS``), the worker ends a job ``failed`` with the error's code and message.
"""

from __future__ import annotations

from typing import Any


class DomainError(Exception):
    """A request that cannot be done as asked: ``code`` (snake_case) names the problem, ``message`` explains it."""

    def __init__(self, code: str, message: str, details: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.details = details


class NotFound(DomainError):
    """Something named does not exist (a dataset, sequence, model, checkpoint)."""


class Invalid(DomainError):
    """The parameters are wrong (an unknown method or preset, a size, a split without data)."""


class Conflict(DomainError):
    """Doing it would overwrite or contradict what is stored."""


class Unavailable(DomainError):
    """A dependency (Redis, the model registry) cannot be reached now."""
