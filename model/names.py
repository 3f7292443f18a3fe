"""Names of the library's choices (splits, schedules, tone maps, training devices): plain constants, no imports,
so the training settings (and the CLI options derived from them) load without torch."""

SPLITS = ("train", "validation", "test")
SCHEDULES = ("cosine", "step", "constant")  # learning-rate schedules after the linear warm-up
TONEMAPS = ("log", "mulaw", "linear")  # what the training loss compares (model.training.losses)
TRAIN_DEVICES = ("auto", "cpu", "cuda")
# The stability suite's scenarios, in report order (model.evaluation.stability describes and builds each; a test
# holds the two equal): one per generator scene, then those derived from one clean sequence.
STABILITY_SCENARIOS = ("moving_object", "moving_light", "camera_cut", "fast_camera", "metals", "glass",
                       "dark_fireflies", "visible_emitter", "orbiting_light", "sliding_over_texture", "clean",
                       "first_frames", "exposure_bright", "exposure_dark", "nan_inf_color", "nan_inf_guides",
                       "zero_motion", "garbage_motion", "missing_buffers")
