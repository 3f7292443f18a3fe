"""Names every layer shares: dataset splits, job kinds, states and devices, the queues, the auto model name.

Plain constants, no imports, so the CLI's --help and the client stay light. ``SPLITS`` equals
``model.io.dataset.SPLITS`` (a test checks it).
"""

SPLITS = ("train", "validation", "test")

# The kinds of core.jobs.kinds.KINDS, as plain names for the client (a test holds them equal).
JOB_KINDS = ("generate", "train", "evaluate", "benchmark", "infer", "fit", "stability")
JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINISHED_STATES = frozenset({"succeeded", "failed", "cancelled"})
DEVICES = ("cpu", "gpu")
QUEUES = ("cpu", "gpu")  # Celery queues; a job on device D goes to queue D
QUEUE_FOR_DEVICE = {"cpu": "cpu", "gpu": "gpu"}

AUTO_MODEL = "auto"  # POST /sessions {"model": "auto"} chooses a version: no registered model may take the name
AUTO_MODEL_RESERVED = (f"{AUTO_MODEL!r} is reserved: sessions read model {AUTO_MODEL!r} as 'choose a version for "
                       "me', so a model of that name could never be opened; choose another name")
