"""Celery tasks of the service: one task, ``workers.tasks.jobs.run_job(job_id)``, runs every job kind.

``jobs`` holds the task, the execution around every kind (lease, watchdog, log, final state) and worker-start
recovery of orphaned jobs; ``kinds`` maps each kind to its module (``generate``, ``train``, ``evaluate`` for
evaluate and benchmark, ``infer``), which checks the kind's parameters (in the API) and runs it (in the worker).
"""
