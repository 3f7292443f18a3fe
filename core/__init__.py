"""What the API, the workers and the CLI share: settings, storage, errors, job specs, job store, tracking, registry.

Imports only ``model`` and third-party libraries (never Celery or FastAPI); see docs/architecture.md.
"""
