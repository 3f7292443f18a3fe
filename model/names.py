"""Names of the library's choices (splits, schedules, tone maps, training devices): plain constants, no imports,
so the training settings (and the CLI options derived from them) load without torch."""

SPLITS = ("train", "validation", "test")
SCHEDULES = ("cosine", "step", "constant")  # learning-rate schedules after the linear warm-up
TONEMAPS = ("log", "mulaw", "linear")  # what the training loss compares (model.training.losses)
TRAIN_DEVICES = ("auto", "cpu", "cuda")
