"""Celery tasks of the service: one task, ``workers.tasks.jobs.run_job(job_id)``, runs every job kind.

``jobs`` holds the task, the execution around every kind (lease, watchdog, log, final state) and worker-start
recovery of orphaned jobs; ``kinds`` maps each kind to the module that runs it (``generate``, ``train``,
``evaluate`` for evaluate and benchmark, ``infer``, ``fit``). Each kind's check, run by the API before
queueing, is in ``core.jobs``.
"""
