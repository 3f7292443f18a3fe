"""The job tests' fixtures (defined in fixtures.py, which tests outside this folder import too)."""

from tests.workers.tasks.fixtures import settings, storage, store  # noqa: F401
