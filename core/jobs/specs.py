"""Job specifications: the parameters of each job kind (pydantic, strict), shared by the API and the workers."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from core.names import (AUTO_MODEL, AUTO_MODEL_RESERVED, DEVICES, ID_MAX_LENGTH, ID_PATTERN, JOB_KINDS, JOB_STATES,
                        RESERVED_ALIAS_PATTERN, SPLITS)
from model.names import STABILITY_SCENARIOS
from model.training.training_settings import FitTrainingSettings, TrainingSettings


JobKind = Literal[JOB_KINDS]
JobState = Literal[JOB_STATES]
JobDevice = Literal[DEVICES]
JobSplit = Literal[SPLITS]

# Job bodies are validated strictly (strict=True on every model below): a value must have its documented JSON
# type, so `"steps": "100"` or `"overwrite": 0` is a 422 naming the field rather than silently coerced.
# A stored id (dataset, registered model name): one safe path component, as core.storage.checked_id.
_ID = {"pattern": ID_PATTERN, "max_length": ID_MAX_LENGTH}


def _registrable(name: str | None) -> str | None:
    if name == AUTO_MODEL:
        raise ValueError(f"register_as {AUTO_MODEL_RESERVED}")
    return name


class GenerateParams(BaseModel):
    """Render scene recipes with Mitsuba 3 into a stored dataset (created when it does not exist)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "scenes": ["diffuse_room", "metals"], "frames": 16, "size": [128, 128],
        "ref_spp": 1024, "scales": [1, 2], "seed": 0, "split": "train"}]})

    dataset: str = Field(**_ID, description="dataset id; created when it does not exist")
    scenes: list[str] = Field(min_length=1, max_length=64,
                              description="scene recipes (see `denoiser scenes`), or ['all']")
    frames: int = Field(16, ge=1, le=10_000, description="frames per sequence")
    size: int | list[int] = Field([128, 128], description="render resolution: N or [width, height]")
    ref_spp: int = Field(1024, ge=1, le=1 << 20, description="samples per pixel of the references")
    albedo_spp: int = Field(16, ge=1, le=4096, description="first-hit samples per pixel of the reference albedos")
    max_depth: int = Field(6, ge=1, le=64, description="longest path (1: directly visible emitters only)")
    scales: list[Literal[1, 2, 4]] = Field([1, 2], min_length=1, description="reference scales to store")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="seed of the scene variation and of the noise")
    split: JobSplit = Field("train", description="split the new sequences join")
    half: bool = Field(False, description="store EXR channels as half floats")
    jitter: bool = Field(True, description="Halton(2,3) sub-pixel jitter per frame; false: every sample at the pixel "
                                           "centre, as renderers without TAA jitter write frames")
    overwrite: bool = Field(False, description="replace sequences of the same name (SCENE_sSEED)")

    @field_validator("size")
    @classmethod
    def _size_pair(cls, value: int | list[int]) -> list[int]:
        pair = [value, value] if isinstance(value, int) else list(value)
        if len(pair) != 2 or not all(1 <= v <= 4096 for v in pair):
            raise ValueError("size must be N or [width, height], each between 1 and 4096")
        return pair

    @field_validator("scales")
    @classmethod
    def _sorted_scales(cls, value: list[int]) -> list[int]:
        return sorted(set(value))


class TrainParams(TrainingSettings):
    """Train a learned method on a stored dataset; checkpoints under the job folder, MLflow run, registered model.

    Every training option is ``model.training.training_settings.TrainingSettings``' (the CLI's ``denoiser train`` options
    too); the fields a client must not set (data and output paths, device, resume, tracking server) are left out
    there, in ``RUN_FIELDS``, and the worker sets them (``core.jobs.train.train_config``)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [
        {"dataset": "rooms", "method": "wskpn:s", "scale": 1, "steps": 2000, "crop": 64, "batch": 4,
         "frames_per_sample": 4, "lr": 0.001, "world_size": 2, "register_as": "wskpn-s-rooms", "seed": 0,
         "validate_every": 500, "checkpoint_every": 250},
        {"dataset": "rooms", "method": "jnds:s-int8", "init_from": "models:/jnds-s-x1@champion", "epochs": 2,
         "lr": 0.0001, "schedule": "constant", "warmup_steps": 0, "temporal_weight": 0.5,
         "register_as": "jnds-s-int8-rooms"}]})

    dataset: str = Field(**_ID, description="id of a stored dataset")
    track: bool = Field(True, description="log to MLflow and register the model")
    nodes: int = Field(1, ge=1, le=64, description="workers of the job's queue (machines) its ranks run on, "
                       "world_size / nodes on each (torchrun, c10d rendezvous); world_size defaults to nodes")
    _register_as_not_auto = field_validator("register_as")(_registrable)

    @model_validator(mode="before")
    @classmethod
    def _one_rank_per_node_by_default(cls, data):
        if isinstance(data, dict) and "world_size" not in data and isinstance(data.get("nodes"), int):
            return {**data, "world_size": data["nodes"]}
        return data

    @model_validator(mode="after")
    def _ranks_split_over_nodes(self) -> TrainParams:
        if self.world_size % self.nodes:
            raise ValueError(f"world_size {self.world_size} (all ranks) does not split evenly over {self.nodes} "
                             f"nodes")
        return self


class EvaluateParams(BaseModel):
    """The benchmark protocol (model.evaluation.evaluate) for the given methods on one split of a stored dataset."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "split": "test", "scale": 1,
        "methods": ["identity", "oidn:high", "models:/wskpn-s-rooms@champion"], "frames": 32}]})

    dataset: str = Field(**_ID, description="id of a stored dataset")
    split: JobSplit = Field("test", description="split to evaluate on")
    scale: Literal[1, 2] = Field(1, description="output / render resolution ratio; the data needs references at it")
    methods: list[str] = Field(min_length=1, max_length=64, description="registry NAME[:PRESET], model refs "
                               "models:/NAME/VERSION or models:/NAME@ALIAS, or checkpoints under jobs/")
    frames: int | None = Field(None, ge=1, le=100_000, description="first N frames of each sequence (none: all)")
    vdp: bool = Field(True, description="compute FovVideoVDP JOD (the slowest metric)")
    oidn_timing: bool = Field(True, description="time OIDN-high in the same run (speed ratios)")
    threads: int | None = Field(None, ge=1, le=1024, description="torch threads for the run")
    track: bool = Field(True, description="log the report and metrics to MLflow")


class BenchmarkParams(EvaluateParams):
    """``evaluate`` at one scale or both over a method list that defaults to the non-learned baselines with OIDN
    and OIDN + TAA at their three presets; adds the benchmark table and charts."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "split": "test", "scale": 1, "frames": 32}]})

    scale: Literal[1, 2, "both"] = Field(1, description="output / render resolution ratio; both: 1 and 2, each "
                                                        "method at the scales it runs at")  # type: ignore[assignment]
    methods: list[str] | None = Field(None, min_length=1, max_length=64,  # type: ignore[assignment]
                                      description="non-learned registry methods NAME[:PRESET] (learned ones as for "
                                                  "evaluate); none: every non-learned method at its default "
                                                  "preset, and oidn and oidn-taa at all three")
    all_presets: bool = Field(False, description="every preset of each non-learned method (of those in methods "
                                                 "when given, unless a preset is named)")
    include_learned: list[str] | None = Field(
        None, min_length=1, max_length=64, description="trained models added to the methods: model references "
        "models:/NAME[/VERSION|@ALIAS], pretrained model names or checkpoint files")


class InferParams(BaseModel):
    """Run a model over stored sequences with its history carried frame to frame; EXR outputs per frame."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "model": "models:/wskpn-s-rooms@champion", "split": "test"}]})

    dataset: str = Field(**_ID, description="id of a stored dataset")
    model: str = Field(min_length=1, max_length=500, description="model ref, registry NAME[:PRESET] or checkpoint")
    split: JobSplit | None = Field(None, description="every sequence of this split")
    sequences: list[str] | None = Field(None, min_length=1, max_length=10_000, description="these sequences")
    scale: Literal[1, 2] | None = Field(None, description="output scale (none: a checkpoint's own, else 1)")

    @model_validator(mode="after")
    def _one_selection(self) -> InferParams:
        if self.split is not None and self.sequences is not None:
            raise ValueError("give split or sequences, not both (neither: every sequence of the dataset)")
        return self


# --- fit jobs (right-sizing, model.fit): the smallest preset of a family that meets a target -----------------

class FitParams(FitTrainingSettings):
    """Train (or reuse) a ladder of a learned family's presets, measure each on the validation split and in ms per
    frame, and register the smallest that meets the target with an alias (docs/fit.md).

    The training options are ``model.training.training_settings.FitTrainingSettings``' (those of a train job but the
    method, world_size, validate_every and init_from), as the CLI's ``denoiser fit``."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [
        {"dataset": "rooms", "method": "wskpn", "presets": ["xs", "s", "m", "l"], "target": "psnr=30",
         "steps": 2000, "register_as": "wskpn-rooms-fit", "alias": "fitted"},
        {"dataset": "rooms", "method": "wskpn", "target": "ms=20@128x128", "steps": 2000, "threads": 2}]})

    dataset: str = Field(**_ID, description="id of a stored dataset")
    method: str = Field(min_length=1, max_length=100, pattern=r"^[A-Za-z0-9_]+$",
                        description="learned registry method family (no preset), e.g. wskpn")
    presets: list[str] | None = Field(None, min_length=1, max_length=32,
                                      description="presets on the ladder (none: the family's presets without a "
                                                  "variant suffix, e.g. xs, s, m, l)")
    target: str = Field(min_length=1, max_length=100,
                        description="psnr=DB (validation PSNR >= DB), flip=E (validation FLIP <= E), "
                                    "ms=MS[@WxH] (ms per frame <= MS at render size WxH, then the best PSNR), "
                                    "within=DB (PSNR >= the largest preset's - DB)")
    time_at: list[int] = Field([256, 256], min_length=2, max_length=2,
                               description="[width, height] of the render frames timed when the target is not ms")
    timing_frames: int = Field(10, ge=1, le=10_000, description="frames timed per preset (after 3 warm-up frames)")
    _register_as_not_auto = field_validator("register_as")(_registrable)
    alias: str = Field("fitted", pattern=r"^[A-Za-z_][A-Za-z0-9_-]{0,63}$",
                       json_schema_extra={"not": {"pattern": RESERVED_ALIAS_PATTERN}},
                       description="alias set on the chosen version")
    track: bool = Field(True, description="log to MLflow, register versions and set the alias (false: only the "
                                          "ladder files in the job folder)")

    @field_validator("time_at")
    @classmethod
    def _positive_size(cls, value: list[int]) -> list[int]:
        if not all(1 <= v <= 8192 for v in value):
            raise ValueError("time_at must be [width, height], each between 1 and 8192")
        return value


# --- stability jobs (model.evaluation.stability): hard scenarios and corrupted inputs --------------------------

class StabilityParams(BaseModel):
    """The stability suite: methods on a stored dataset's hard scenes and on corrupted copies of one clean sequence;
    where each fails worst (largest drop of its PSNR gain over the noisy input) and which ghosts least."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "methods": ["svgf", "oidn-taa:high", "models:/wskpn-s-rooms@champion"],
        "scenarios": ["moving_light", "clean", "nan_inf_color"], "frames": 8}]})

    dataset: str = Field(**_ID, description="id of a stored dataset")
    methods: list[str] = Field(min_length=1, max_length=64, description="as for evaluate: registry NAME[:PRESET], "
                               "model references, pretrained model names or checkpoints")
    scenarios: list[Literal[STABILITY_SCENARIOS]] | None = Field(None, min_length=1, description="scenarios to "
                                                                 "run (none: all that the dataset allows)")
    scale: Literal[1, 2] = Field(1, description="output / render resolution ratio")
    base: str | None = Field(None, **_ID, description="clean sequence the derived scenarios are made "
                             "from (none: a diffuse_room one, else the first that is no scene scenario)")
    frames: int | None = Field(None, ge=1, le=100_000, description="first N frames of each sequence (none: all)")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="seed of the corruptions (NaN/Inf pixels, garbage motion)")
    vdp: bool = Field(False, description="compute FovVideoVDP JOD too (the slowest metric)")
    threads: int | None = Field(None, ge=1, le=1024, description="torch threads for the run")
    track: bool = Field(True, description="log the report and scores to MLflow")
