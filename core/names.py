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

# A stored id (dataset, sequence, registered model name): one safe path component. Letters, digits, '.', '_', '-',
# starting with a letter or digit, no '..', at most ID_MAX_LENGTH characters. Written without look-arounds so that
# JSON schema tools (API testers, generated clients) can read it; core.storage.checked_id applies it.
ID_PATTERN = r"^[A-Za-z0-9](?:[A-Za-z0-9_-]|\.[A-Za-z0-9_-])*\.?$"
ID_MAX_LENGTH = 128
# Job and session ids are generated (uuid4().hex).
HEX_ID_PATTERN = r"^[0-9a-f]{32}$"
# A registry alias name (MLflow also takes non-ASCII word characters; the API documents the ASCII ones).
ALIAS_PATTERN = r"^[A-Za-z0-9_-]+$"
ALIAS_MAX_LENGTH = 255
RESERVED_ALIAS_PATTERN = r"^(?:[vV][0-9]+|[Ll][Aa][Tt][Ee][Ss][Tt])$"  # MLflow keeps these for versions


def at_most_pattern(limit: int) -> str:
    """A regular expression for the decimal numbers 1..limit without leading zeros (what a JSON schema can say of a
    number written as a string, e.g. a model version)."""
    digits = str(limit)
    options = [f"[1-9][0-9]{{0,{len(digits) - 2}}}"] if len(digits) > 1 else []
    for position, digit in enumerate(digits):
        low = "1" if position == 0 else "0"
        top = int(digit) - (0 if position == len(digits) - 1 else 1)
        if top >= int(low):
            rest = len(digits) - position - 1
            options.append(digits[:position] + (f"[{low}-{top}]" if top > int(low) else low) +
                           (f"[0-9]{{{rest}}}" if rest else ""))
    return "^(?:" + "|".join(options) + ")$"
