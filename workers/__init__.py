"""Celery workers that run the jobs (generate, train, evaluate, benchmark, infer, fit); see docs/architecture.md."""
