"""Every training option, declared once: name, default, range, help text and cross-field checks.

``TrainingSettings`` holds what a training takes that anyone may choose, a REST client included. Everything else
derives from it, so names, defaults and checks cannot drift:

- ``TrainConfig`` (the library's config, ``model.training.train``) adds where and how a run executes (``RUN_FIELDS``);
- ``FitTrainingSettings``, the training options of a fit (``model.fit``), is it without ``NOT_FIT_OPTIONS``;
- the REST job parameters (``core.jobs.specs.TrainParams``, ``FitParams``) subclass them, adding the dataset;
- the ``denoiser train`` and ``denoiser fit`` options are generated from the fields (``cli.options``);
- the DDP launcher (``workers.ddp``) passes a ``TrainConfig`` to its ranks as JSON.

Importable without torch (the CLI builds its ``--help`` from it).
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model, model_validator

from model.names import SCHEDULES, SPLITS, TONEMAPS, TRAIN_DEVICES

# A registered model name: one safe path component (it names folders and MLflow models).
REGISTERED_NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$"
MAX_STEPS = 10_000_000


class _TrainingChecks(BaseModel):
    """The cross-field checks of the training options. Models that take a subset of the options (a fit's) run
    the checks of the fields they have."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _epochs_instead_of_steps(cls, data: Any) -> Any:
        # steps has a default; asking for epochs (and no steps) means "epochs instead of the default steps".
        if isinstance(data, dict) and data.get("epochs") is not None and "steps" not in data:
            return {**data, "steps": None}
        return data

    @model_validator(mode="after")
    def _consistent(self) -> _TrainingChecks:
        steps, epochs = getattr(self, "steps", None), getattr(self, "epochs", None)
        if (steps is None) == (epochs is None):
            raise ValueError(f"give exactly one of steps and epochs (got steps={steps}, epochs={epochs})")
        world_size = getattr(self, "world_size", 1)
        if self.batch % world_size:
            raise ValueError(f"batch {self.batch} does not split evenly over {world_size} ranks (world_size)")
        if self.loss_skip_frames >= self.frames_per_sample:
            raise ValueError(f"loss_skip_frames ({self.loss_skip_frames}) must be below frames_per_sample "
                             f"({self.frames_per_sample}): some frame must count")
        return self


class TrainingSettings(_TrainingChecks):
    """What a training takes (besides its data and where it runs); see the module's docstring."""

    method: str = Field(min_length=1, max_length=200,
                        description="learned method from the registry, NAME[:PRESET] (see 'denoiser methods')")
    scale: Literal[1, 2] = Field(1, description="output / render resolution; the data needs references at it")
    steps: int | None = Field(1000, ge=1, le=MAX_STEPS, description="optimizer steps (exactly one of steps and "
                                                                    "epochs)")
    epochs: int | None = Field(None, ge=1, le=100_000, description="passes over the training samples, instead of "
                                                                   "steps")
    crop: int = Field(64, ge=1, le=4096, description="crop size in render pixels (the reference crop is SCALE "
                                                     "times larger)")
    frames_per_sample: int = Field(4, ge=1, le=256, description="consecutive frames unrolled per sample")
    batch: int = Field(4, ge=1, le=4096, description="global batch size, split evenly over the ranks")
    lr: float = Field(1e-3, gt=0, le=10, description="Adam learning rate")
    schedule: Literal[SCHEDULES] = Field("cosine", description="learning-rate schedule after the warm-up")
    warmup_steps: int = Field(50, ge=0, le=MAX_STEPS, description="steps of linear learning-rate warm-up")
    lr_step_every: int | None = Field(None, ge=1, le=MAX_STEPS, description="step schedule: decay every N steps "
                                                                            "(none: every third of the training)")
    lr_step_gamma: float = Field(0.3, gt=0, le=1, description="step schedule: factor of each decay")
    min_lr_ratio: float = Field(0.01, ge=0, le=1, description="cosine schedule: the learning rate ends at "
                                                              "lr * min_lr_ratio")
    grad_clip: float = Field(1.0, ge=0, le=1e6, description="largest gradient norm (0: no clipping)")
    spatial_weight: float | None = Field(None, ge=0, le=1e6, description="weight of the spatial (SMAPE) loss "
                                                                         "(none: the method's own, 1 for most)")
    temporal_weight: float | None = Field(None, ge=0, le=1e6, description="weight of the temporal loss (none: "
                                                                          "the method's own, 0.25 for most)")
    tonemap: Literal[TONEMAPS] = Field("log", description="what the loss compares: log, mu-law or linear radiance")
    display_weight: float = Field(0.0, ge=0, le=1e6, description="weight of a mean squared error on display-encoded "
                                                                 "images, clip(x, 0, 1) ** (1/2.2): what PSNR "
                                                                 "measures (0: none)")
    loss_skip_frames: int = Field(0, ge=0, le=255, description="leave the first K frames of each sample out of "
                                                               "the loss")
    augment: bool = Field(True, description="flips, brightness and a random rotation of the normals' world frame")
    shipped_settings: bool = Field(True, description="a model trained from nothing runs, and trains with, the "
                                                     "run-time settings its family's shipped models run (fused: "
                                                     "the stale-history tests, OIDN on a sample mean, the texture "
                                                     "detail at 2x); off: none. A fine-tune keeps its start's")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="seed of the weights, crops and augmentation")
    train_split: Literal[SPLITS] = Field("train", description="split to train on")
    validation_split: Literal[SPLITS] = Field("validation", description="split to validate on (may be empty for a "
                                                                        "training: then no validation)")
    validate_every: int = Field(500, ge=0, le=MAX_STEPS, description="validate every N steps (0: only at the end)")
    validation_frames: int | None = Field(None, ge=1, le=100_000, description="frames per validation sequence "
                                                                              "(none: all)")
    checkpoint_every: int = Field(500, ge=0, le=MAX_STEPS, description="write the last checkpoint every N steps "
                                                                       "(0: only at the end)")
    world_size: int = Field(1, ge=1, le=64, description="DDP ranks (processes)")
    threads: int | None = Field(None, ge=1, le=1024, description="torch threads per rank (none: torch's own, or "
                                                                 "the cores shared out among CPU ranks)")
    experiment: str = Field("denoiser", min_length=1, max_length=200, description="MLflow experiment name")
    register_as: str | None = Field(None, pattern=REGISTERED_NAME_PATTERN,
                                    description="registered model name (none: METHOD-PRESET-xSCALE; a fit's: "
                                                "FAMILY-fit-xSCALE)")
    init_from: str | None = Field(None, min_length=1, max_length=500,
                                  description="start from these weights instead of random ones (fine-tuning): a "
                                              "checkpoint, a pretrained model or a registered model "
                                              "(models:/NAME@ALIAS); same method and scale (a float32 JNDS "
                                              "starts its -int8 preset for quantization-aware training)")


# Where and how a run executes, set by whoever runs it (the CLI from its options, the service from its own settings
# and the job's folder), so not in TrainingSettings: a REST client must not choose server paths (data, out), a
# device other than its job's queue, whether an old run is resumed, or the tracking server.
RUN_FIELDS = ("data", "out", "resume", "device", "tracking_uri")


class TrainConfig(TrainingSettings):
    """The library's training config: ``TrainingSettings`` plus where and how the run executes (``RUN_FIELDS``)."""

    data: str = Field(description="dataset folder")
    out: str = Field("runs/train", description="output folder of the checkpoints (last.pt, best.pt)")
    resume: bool = Field(True, description="continue from OUT/last.pt when it exists")
    device: Literal[TRAIN_DEVICES] = Field("auto", description="auto: CUDA when available (NCCL between ranks), "
                                                               "else CPU (gloo)")
    tracking_uri: str | None = Field(None, description="MLflow tracking URI (none: the service's, "
                                                       "DENOISER_TRACKING_URI, else the SQLite store in "
                                                       "DENOISER_DATA_DIR)")

    def check(self) -> None:
        """Check the settings again (after fields were changed in place); ValueError naming the field."""
        type(self).model_validate(self.model_dump())

    def to_dict(self) -> dict[str, Any]:
        return self.model_dump()

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        unknown = sorted(set(values) - set(cls.model_fields))
        if unknown:
            raise ValueError(f"unknown training settings: {', '.join(unknown)}")
        return cls.model_validate(values)

    def frame_weights(self) -> list[float]:
        return [0.0] * self.loss_skip_frames + [1.0] * (self.frames_per_sample - self.loss_skip_frames)

    def total_steps(self, samples: int) -> int:
        return self.steps if self.steps is not None else self.epochs * math.ceil(samples / self.batch)


# Training options a fit does not take: its method is a family (the presets are chosen apart), it trains each
# preset in one process, measures each preset itself instead of validating during training, and one checkpoint
# cannot start presets of different sizes.
NOT_FIT_OPTIONS = ("method", "world_size", "validate_every", "init_from")


def training_fields(exclude: tuple[str, ...] = ()) -> dict[str, Any]:
    """TrainingSettings' fields but ``exclude``, as ``create_model`` takes them (annotation, FieldInfo)."""
    return {name: (field.annotation, field) for name, field in TrainingSettings.model_fields.items()
            if name not in exclude}


FitTrainingSettings = create_model("FitTrainingSettings", __base__=_TrainingChecks, __module__=__name__,
                                   __doc__="The training options of a fit: TrainingSettings without "
                                           "NOT_FIT_OPTIONS.",
                                   **training_fields(exclude=NOT_FIT_OPTIONS))
