"""Request and response bodies of the API (pydantic v2), one section per resource.

Input and output models are separate classes; every model carries an example (``json_schema_extra``) so the
OpenAPI document shows a complete request or response for each endpoint.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

AUTO_MODEL = "auto"  # POST /sessions {"model": "auto"} chooses a version: no registered model may take the name
AUTO_MODEL_RESERVED = (f"{AUTO_MODEL!r} is reserved: sessions read model {AUTO_MODEL!r} as 'choose a version for "
                       "me', so a model of that name could never be opened; choose another name")

# =========================================================================================================
# Health and readiness (GET /health, GET /ready)
# =========================================================================================================

CheckStatus = Literal["ok", "down", "skipped"]


class Health(BaseModel):
    """Liveness: the process answers HTTP. Says nothing about Redis, MLflow or workers (see /ready)."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"status": "ok"}]})

    status: Literal["ok"] = "ok"


class DependencyCheck(BaseModel):
    """One dependency's state; ``detail`` says what was tried and, when down, what failed."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"status": "ok", "detail": "PING answered in 0.4 ms"}]
    })

    status: CheckStatus = Field(description="ok, down, or skipped (not checkable from here)")
    detail: str = Field(description="what was checked and, when down, why")


class Readiness(BaseModel):
    """Whether this API can serve; answered with 200 when ``down`` is empty, else 503 with this body. Workers are
    listed from their heartbeats but do not decide it."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [
            {
                "status": "ready",
                "redis": {"status": "ok", "detail": "PING answered in 0.4 ms"},
                "storage": {"status": "ok", "detail": "data folder is writable"},
                "mlflow": {"status": "ok", "detail": "GET /health answered 200"},
                "workers": ["celery@gpu-box", "celery@cpu-box"],
                "workers_detail": "2 workers alive (heartbeat within 30 s); celery@gpu-box runs job 7f3c...",
                "down": [],
            },
            {
                "status": "unavailable",
                "redis": {"status": "down", "detail": "PING failed (ConnectionError; see the API log)"},
                "storage": {"status": "ok", "detail": "data folder is writable"},
                "mlflow": {"status": "ok", "detail": "sqlite store folder is writable"},
                "workers": [],
                "workers_detail": "not checked: Redis (where workers write their heartbeats) is down",
                "down": ["redis"],
            },
        ]
    })

    status: Literal["ready", "unavailable"]
    redis: DependencyCheck
    storage: DependencyCheck
    mlflow: DependencyCheck
    workers: list[str] = Field(description="host names of the workers whose heartbeat is alive")
    workers_detail: str = Field(description="how many workers are alive and which jobs they run, or why unknown")
    down: list[str] = Field(description="the dependencies that are down: any of redis, storage, mlflow")


# =========================================================================================================
# Datasets (/datasets)
# =========================================================================================================

Split = Literal["train", "validation", "test"]


class SequenceInfo(BaseModel):
    """One stored sequence: a folder of frame bundle EXRs plus its manifest."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "name": "kitchen_0",
            "split": "train",
            "scene": "kitchen",
            "frames": 64,
            "width": 640,
            "height": 360,
            "scales": [1, 2],
            "buffers": ["color", "albedo", "normal", "depth", "motion", "reference"],
            "camera_cuts": [0],
        }]
    })

    name: str
    split: Split
    scene: str | None = Field(description="scene recipe the sequence was rendered from, when known")
    frames: int = Field(description="number of frames; frame i has frame_index i")
    width: int = Field(description="render resolution, pixels")
    height: int
    scales: list[int] = Field(description="reference scales present (target = scale x render resolution)")
    buffers: list[str] = Field(description="buffers present in the frames (model.frames.BUFFERS names)")
    camera_cuts: list[int] = Field(description="frame indices that start after a camera cut")


class SplitSummary(BaseModel):
    """Per split totals, read from the manifests only."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"sequences": 3, "frames": 192, "scenes": ["kitchen", "sponza"], "resolutions": [[640, 360]],
                      "scales": [1, 2]}]
    })

    sequences: int
    frames: int
    scenes: list[str]
    resolutions: list[list[int]] = Field(description="distinct render resolutions as [width, height]")
    scales: list[int]


class DatasetSummary(BaseModel):
    """One entry of GET /datasets."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"id": "kitchens", "sequences": 4, "frames": 256, "scenes": ["kitchen", "sponza"],
                      "splits": {"train": 3, "validation": 1, "test": 0}}]
    })

    id: str
    sequences: int
    frames: int
    scenes: list[str]
    splits: dict[Split, int] = Field(description="number of sequences in each split")


class DatasetDetail(BaseModel):
    """GET /datasets/{id}: every sequence with its split, frames, buffers, resolution and scales."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "id": "kitchens",
            "frames": 64,
            "scenes": ["kitchen"],
            "splits": {
                "train": {"sequences": 1, "frames": 64, "scenes": ["kitchen"], "resolutions": [[640, 360]],
                          "scales": [1, 2]},
                "validation": {"sequences": 0, "frames": 0, "scenes": [], "resolutions": [], "scales": []},
                "test": {"sequences": 0, "frames": 0, "scenes": [], "resolutions": [], "scales": []},
            },
            "sequences": [{
                "name": "kitchen_0", "split": "train", "scene": "kitchen", "frames": 64, "width": 640,
                "height": 360, "scales": [1, 2],
                "buffers": ["color", "albedo", "normal", "depth", "motion", "reference"], "camera_cuts": [0],
            }],
        }]
    })

    id: str
    frames: int = Field(description="frames over all sequences")
    scenes: list[str]
    splits: dict[Split, SplitSummary]
    sequences: list[SequenceInfo]


class StagedSequence(BaseModel):
    """A sequence being uploaded frame by frame; it joins the dataset on POST .../commit."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "dataset": "kitchens", "sequence": "kitchen_7", "split": "validation", "scene": "kitchen",
            "frames": 3, "next_frame_index": 3, "width": 640, "height": 360, "scales": [1, 2],
            "buffers": ["color", "albedo", "normal", "depth", "motion", "reference"],
        }]
    })

    dataset: str
    sequence: str
    split: Split
    scene: str | None
    frames: int = Field(description="frames received so far")
    next_frame_index: int = Field(description="the frame_index the next upload must have")
    width: int
    height: int
    scales: list[int]
    buffers: list[str]


# =========================================================================================================
# Models (/models): the MLflow registry
# =========================================================================================================

from datetime import datetime  # noqa: E402  (this section's own import; may move to the top of the file)


class ModelSummary(BaseModel):
    """One entry of GET /models: a registered model, its newest version and its aliases."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "description": "JNDS xs, 2x upscaling, trained on kitchens",
                      "latest_version": "3", "aliases": {"champion": "2"}}]
    })

    name: str
    description: str | None = Field(None, description="the registered model's description, if any")
    latest_version: str | None = Field(description="highest version number; null when no version is registered")
    aliases: dict[str, str] = Field(description="alias -> version it points at")


class ModelVersionOut(BaseModel):
    """One registered version: what it is (method, preset, scale, size) and what it measured."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "name": "jnds-xs-x2", "version": "2", "run_id": "b260b403e5dc4cffa4c56a75595a40cb",
            "created_at": "2026-11-22T06:30:57.715000Z", "method": "jnds", "preset": "xs", "scale": 2,
            "params": 16228, "flops_per_pixel": 13416.0,
            "metrics": {"validation_psnr": 31.42, "ms_per_frame": 4.8},
            "tags": {"method": "jnds", "preset": "xs", "scale": "2", "params": "16228",
                     "flops_per_pixel": "13416", "steps": "20000", "validation_psnr": "31.4200"},
            "aliases": ["champion"], "ref": "models:/jnds-xs-x2/2",
        }]
    })

    name: str
    version: str
    run_id: str | None = Field(description="the MLflow run that trained it")
    created_at: datetime | None
    method: str | None = Field(description="registry method name (tag 'method')")
    preset: str | None = Field(description="size preset (tag 'preset')")
    scale: int | None = Field(description="output / render resolution ratio (tag 'scale')")
    params: int | None = Field(description="number of parameters (tag 'params')")
    flops_per_pixel: float | None = Field(description="FLOPs per output pixel of one step (tag 'flops_per_pixel')")
    metrics: dict[str, float] = Field(
        description="measurements recorded on the version: validation_psnr, validation_ssim, ms_per_frame and "
                    "tags 'metric.<name>', when known")
    tags: dict[str, str] = Field(description="every tag of the version, as stored")
    aliases: list[str] = Field(description="aliases pointing at this version")
    ref: str = Field(description="model reference for jobs: models:/NAME/VERSION")


class ModelDetail(ModelSummary):
    """GET /models/{name}: the summary plus every version, oldest first."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "description": None, "latest_version": "2",
                      "aliases": {"champion": "2"},
                      "versions": [ModelVersionOut.model_config["json_schema_extra"]["examples"][0]]}]
    })

    versions: list[ModelVersionOut]


class AliasIn(BaseModel):
    """PUT /models/{name}/aliases/{alias}: the version the alias should point at."""

    model_config = ConfigDict(json_schema_extra={"examples": [{"version": "3"}]})

    version: str = Field(pattern=r"^[1-9][0-9]*$", description="an existing version number of the model",
                         examples=["3"])


class AliasOut(BaseModel):
    """An alias and the version it points at."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "alias": "champion", "version": "2",
                      "model_version": ModelVersionOut.model_config["json_schema_extra"]["examples"][0]}]
    })

    name: str
    alias: str
    version: str
    model_version: ModelVersionOut


# =========================================================================================================
# Sessions (/sessions): streaming inference with server-side history
# =========================================================================================================

OnGap = Literal["reset", "reject"]


from typing import Any  # noqa: E402  (this section's own import)

from pydantic import field_validator as _session_field_validator  # noqa: E402  (this section's own import)
from pydantic import model_validator as _session_validator  # noqa: E402  (this section's own import)


class SessionIn(BaseModel):
    """POST /sessions: which registered model to run (a version, an alias, or neither for the latest), or
    ``"model": "auto"`` with a constraint: the server chooses among registered versions by their tags."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={
        "examples": [{"model": "jnds-xs-x2", "alias": "champion", "on_gap": "reset"},
                     {"model": "jnds-xs-x2", "version": "3", "on_gap": "reject"},
                     {"model": "auto", "max_ms_per_frame": 20, "family": "wskpn"},
                     {"model": "auto", "min_psnr": 30},
                     {"model": "oidn:high"}, {"model": "svgf", "scale": 2}, {"model": "fused-balanced-x1"}]
    })

    model: str = Field(min_length=1, description="registered model name (GET /models), pretrained model name "
                                                 "(denoiser pretrained), a method without weights (oidn:high, "
                                                 "oidn-taa, svgf, accumulation), or 'auto': choose by "
                                                 "max_ms_per_frame / min_psnr", examples=["jnds-xs-x2"])
    version: str | None = Field(None, pattern=r"^[1-9][0-9]*$", description="version number; not with alias")
    alias: str | None = Field(None, min_length=1, description="alias, e.g. champion; not with version")
    on_gap: OnGap = Field("reset", description="a frame_index past the next expected one: 'reset' restarts the "
                                               "history (X-History: reset-gap), 'reject' answers 409 frame_gap")
    # model "auto" only (README, "Right-sizing"):
    max_ms_per_frame: float | None = Field(None, gt=0, allow_inf_nan=False,
                                           description="auto: the version's recorded ms_per_frame must be at most "
                                                       "this; alone, the best validation PSNR within it wins")
    min_psnr: float | None = Field(None, gt=0, allow_inf_nan=False,
                                   description="auto: validation PSNR (dB) at least this; the smallest such "
                                               "version wins (FLOPs per pixel)")
    family: str | None = Field(None, pattern=r"^[A-Za-z0-9_]+$", description="auto: only versions of this method")
    scale: Literal[1, 2] | None = Field(None, description="auto: only versions at this output scale; a method: its "
                                                        "output scale (default 1); a model: must be its own")
    layout: str | dict[str, Any] = Field(
        "denoiser", description="how the posted frames' EXR channels map to the frame bundle: a built-in layout "
                                "(denoiser, blender-cycles, generic) or a layout object (README, 'Bringing your "
                                "renderer's frames')", examples=["blender-cycles"])

    @_session_field_validator("layout")
    @classmethod
    def _known_layout(cls, value: str | dict[str, Any]) -> str | dict[str, Any]:
        from model.layouts import LayoutError, layout_from_value

        try:
            layout_from_value(value)
        except LayoutError as error:
            raise ValueError(str(error)) from None
        return value

    @_session_validator(mode="after")
    def _auto_fields(self) -> SessionIn:
        auto_fields = [name for name in ("max_ms_per_frame", "min_psnr", "family")
                       if getattr(self, name) is not None]
        if self.model == AUTO_MODEL:
            if self.version is not None or self.alias is not None:
                raise ValueError("model 'auto' chooses a version itself: give no version or alias")
            if self.max_ms_per_frame is None and self.min_psnr is None:
                raise ValueError("model 'auto' needs max_ms_per_frame, min_psnr or both")
        elif auto_fields:
            raise ValueError(f"{', '.join(auto_fields)} only go with model 'auto'")
        return self


class AutoChoiceOut(BaseModel):
    """How a session created with model 'auto' got its version: the constraint, the version's tags, and why."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "name": "wskpn-fit-x1", "version": "2", "method": "wskpn", "preset": "s", "scale": 1,
        "flops_per_pixel": 36260.0, "validation_psnr": 31.2, "ms_per_frame": 14.1,
        "ms_per_frame_resolution": "256x256", "constraint": {"max_ms_per_frame": 20, "family": "wskpn"},
        "candidates": 4,
        "reason": "wskpn-fit-x1 version 2 (wskpn:s at scale 1, 3.626e+04 FLOPs/px): the best validation PSNR "
                  "(31.20 dB) of the 2 of 4 candidate versions of family 'wskpn' within 20 ms per frame (14.1 ms "
                  "per frame at 256x256, 2 threads)"}]})

    name: str
    version: str
    method: str | None
    preset: str | None
    scale: int | None
    flops_per_pixel: float | None
    validation_psnr: float | None
    ms_per_frame: float | None
    ms_per_frame_resolution: str | None = Field(description="render resolution the ms_per_frame was timed at")
    constraint: dict[str, float | int | str] = Field(description="what the request asked for")
    candidates: int = Field(description="versions that had the tags to be compared")
    reason: str


class SessionModelOut(BaseModel):
    """The model version a session runs."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{"name": "jnds-xs-x2", "version": "2", "alias": "champion", "method": "jnds", "preset": "xs",
                      "scale": 2, "params": 16228}]
    })

    name: str
    version: str | None = Field(description="registered: the version; pretrained: the weights' sha256 prefix; "
                                            "method: null")
    alias: str | None = Field(description="the alias the session was created with (resolved once, at creation)")
    method: str
    preset: str
    scale: int = Field(description="output / render resolution ratio")
    params: int = Field(description="number of parameters")
    source: Literal["registered", "pretrained", "method"] = Field(
        "registered", description="a registered model version, a pretrained model shipped with the service, or a "
                                  "method without weights")


class SessionOut(BaseModel):
    """A session: its model, its stream position and when it expires."""

    model_config = ConfigDict(json_schema_extra={
        "examples": [{
            "id": "0f8fad5bd9cb469fa16570867728950e",
            "model": SessionModelOut.model_config["json_schema_extra"]["examples"][0],
            "created_at": "2026-11-22T06:30:57.715000Z", "last_used_at": "2026-11-22T06:31:02.100000Z",
            "expires_at": "2026-11-22T07:01:02.100000Z", "frames_processed": 42, "next_frame_index": 42,
            "on_gap": "reset", "resolution": [640, 360],
        }]
    })

    id: str
    model: SessionModelOut
    created_at: datetime
    last_used_at: datetime = Field(description="last creation, frame or reset")
    expires_at: datetime = Field(description="last_used_at + the server's session TTL")
    frames_processed: int = Field(description="frames run through the session since it was created")
    next_frame_index: int | None = Field(description="the frame_index that continues the history; null: no "
                                                     "history, any index starts one")
    on_gap: OnGap
    resolution: list[int] | None = Field(description="[width, height] every frame must have until a reset "
                                                      "(set by the first frame); null before it")
    choice: AutoChoiceOut | None = Field(None, description="model 'auto' only: the version chosen and why")
    layout: str | dict[str, Any] = Field("denoiser", description="the layout posted frames are read in")
    token: str | None = Field(None, description="only in the answer to POST /sessions, and only where the server "
                                                "has DENOISER_SESSION_OWNER_TOKENS on: send it as X-Session-Token "
                                                "with every request on this session")


# =========================================================================================================
# Jobs (/jobs): generate, train, evaluate, benchmark and infer jobs run by Celery workers
# =========================================================================================================

# This section's own imports (kept here so the section stays self-contained; they may move to the top).
from datetime import datetime as _datetime  # noqa: E402
from typing import Annotated as _Annotated  # noqa: E402
from typing import Any as _Any  # noqa: E402
from typing import Union as _Union  # noqa: E402

from pydantic import create_model  # noqa: E402
from pydantic import field_validator as _field_validator  # noqa: E402
from pydantic import model_validator as _model_validator  # noqa: E402

JobKind = Literal["generate", "train", "evaluate", "benchmark", "infer", "fit"]
JobState = Literal["queued", "running", "succeeded", "failed", "cancelled"]
JobDevice = Literal["cpu", "gpu"]
JobSplit = Literal["train", "validation", "test"]
# Job bodies are validated strictly (strict=True on every model below): a value must have its documented JSON
# type, so `"steps": "100"` or `"overwrite": 0` is a 422 naming the field rather than silently coerced.
# A stored id (dataset, registered model name): one safe path component, as service.storage.checked_id.
_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$"


def _registrable(name: str | None) -> str | None:
    if name == AUTO_MODEL:
        raise ValueError(f"register_as {AUTO_MODEL_RESERVED}")
    return name


class GenerateParams(BaseModel):
    """Render scene recipes with Mitsuba 3 into a stored dataset (created when it does not exist)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "scenes": ["diffuse_room", "metals"], "frames": 16, "size": [128, 128],
        "ref_spp": 1024, "scales": [1, 2], "seed": 0, "split": "train"}]})

    dataset: str = Field(pattern=_ID_PATTERN, description="dataset id; created when it does not exist")
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
    overwrite: bool = Field(False, description="replace sequences of the same name (SCENE_sSEED)")

    @_field_validator("size")
    @classmethod
    def _size_pair(cls, value: int | list[int]) -> list[int]:
        pair = [value, value] if isinstance(value, int) else list(value)
        if len(pair) != 2 or not all(1 <= v <= 4096 for v in pair):
            raise ValueError("size must be N or [width, height], each between 1 and 4096")
        return pair

    @_field_validator("scales")
    @classmethod
    def _sorted_scales(cls, value: list[int]) -> list[int]:
        return sorted(set(value))


class TrainParams(BaseModel):
    """Train a learned method on a stored dataset; checkpoints under the job folder, MLflow run, registered model."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "method": "wskpn:s", "scale": 1, "steps": 2000, "crop": 64, "batch": 4,
        "frames_per_sample": 4, "lr": 0.001, "world_size": 2, "register_as": "wskpn-s-rooms", "seed": 0,
        "validate_every": 500, "checkpoint_every": 250}]})

    dataset: str = Field(pattern=_ID_PATTERN)
    method: str = Field(min_length=1, max_length=200, description="learned registry method NAME[:PRESET]")
    scale: Literal[1, 2] = Field(1, description="output / render resolution")
    steps: int = Field(1000, ge=1, le=10_000_000, description="optimizer steps")
    crop: int = Field(64, ge=1, le=4096, description="crop size in render pixels")
    batch: int = Field(4, ge=1, le=4096, description="global batch size, split over the ranks")
    frames_per_sample: int = Field(4, ge=1, le=256, description="consecutive frames unrolled per sample")
    lr: float = Field(1e-3, gt=0, le=10, description="Adam learning rate")
    schedule: Literal["cosine", "step", "constant"] = "cosine"
    warmup_steps: int = Field(50, ge=0, le=10_000_000)
    world_size: int = Field(1, ge=1, le=64, description="DDP ranks (processes); >1 runs them on this worker")
    register_as: str | None = Field(None, pattern=_ID_PATTERN,
                                    description="registered model name (none: METHOD-PRESET-xSCALE)")
    _register_as_not_auto = _field_validator("register_as")(_registrable)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    validate_every: int = Field(500, ge=0, le=10_000_000, description="steps (0: only at the end)")
    checkpoint_every: int = Field(500, ge=0, le=10_000_000, description="steps (0: only at the end)")
    train_split: JobSplit = "train"
    validation_split: JobSplit = "validation"
    validation_frames: int | None = Field(None, ge=1, le=100_000, description="frames per validation sequence")
    threads: int | None = Field(None, ge=1, le=1024, description="torch threads per rank")
    experiment: str = Field("denoiser", min_length=1, max_length=200, description="MLflow experiment")
    track: bool = Field(True, description="log to MLflow and register the model")
    init_from: str | None = Field(None, min_length=1, max_length=500,
                                  description="start from these weights instead of random ones (fine-tuning): a "
                                              "registered model (models:/NAME@ALIAS, models:/NAME/VERSION, "
                                              "models:/NAME), a pretrained model's name (denoiser pretrained), or a "
                                              "checkpoint under the data folder's jobs/ or models/; same method "
                                              "and scale (a float32 JNDS may start its -int8 preset)",
                                  examples=["fused-balanced-x1", "models:/fused-balanced-x1@pretrained"])


class EvaluateParams(BaseModel):
    """The benchmark protocol (model.evaluate) for the given methods on one split of a stored dataset."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "split": "test", "scale": 1,
        "methods": ["identity", "oidn:high", "models:/wskpn-s-rooms@champion"], "frames": 32}]})

    dataset: str = Field(pattern=_ID_PATTERN)
    split: JobSplit = "test"
    scale: Literal[1, 2] = 1
    methods: list[str] = Field(min_length=1, max_length=64, description="registry NAME[:PRESET], model refs "
                               "models:/NAME/VERSION or models:/NAME@ALIAS, or checkpoints under jobs/")
    frames: int | None = Field(None, ge=1, le=100_000, description="first N frames of each sequence (none: all)")
    vdp: bool = Field(True, description="compute FovVideoVDP JOD (the slowest metric)")
    oidn_timing: bool = Field(True, description="time OIDN-high in the same run (speed ratios)")
    threads: int | None = Field(None, ge=1, le=1024, description="torch threads for the run")
    track: bool = Field(True, description="log the report and metrics to MLflow")


class BenchmarkParams(EvaluateParams):
    """``evaluate`` over a method list that defaults to the baselines and OIDN's presets; adds a chart."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "split": "test", "scale": 1, "frames": 32}]})

    methods: list[str] | None = Field(None, min_length=1, max_length=64,  # type: ignore[assignment]
                                      description="as for evaluate; none: identity, accumulation, svgf and "
                                                  "oidn:fast/balanced/high (those that run at the scale)")
    include_learned: list[str] | None = Field(
        None, min_length=1, max_length=64, description="trained models added to the methods (as the CLI's "
        "--include-learned): model references models:/NAME[/VERSION|@ALIAS] or checkpoint files in the data folder")


class InferParams(BaseModel):
    """Run a model over stored sequences with its history carried frame to frame; EXR outputs per frame."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [{
        "dataset": "rooms", "model": "models:/wskpn-s-rooms@champion", "split": "test"}]})

    dataset: str = Field(pattern=_ID_PATTERN)
    model: str = Field(min_length=1, max_length=500, description="model ref, registry NAME[:PRESET] or checkpoint")
    split: JobSplit | None = Field(None, description="every sequence of this split")
    sequences: list[str] | None = Field(None, min_length=1, max_length=10_000, description="these sequences")
    scale: Literal[1, 2] | None = Field(None, description="output scale (none: a checkpoint's own, else 1)")

    @_model_validator(mode="after")
    def _one_selection(self) -> InferParams:
        if self.split is not None and self.sequences is not None:
            raise ValueError("give split or sequences, not both (neither: every sequence of the dataset)")
        return self


def _job_create(kind: str, params: type[BaseModel], device: str = "cpu") -> type[BaseModel]:
    """The POST /jobs body of one kind: ``{"kind": KIND, "params": PARAMS, "device": ...}`` as a model named
    ``<Kind>JobCreate`` (its OpenAPI schema name), with an example built from ``params``' first example."""
    example = {"kind": kind, "params": params.model_config["json_schema_extra"]["examples"][0], "device": device}
    return create_model(
        f"{kind.capitalize()}JobCreate",
        __config__=ConfigDict(extra="forbid", strict=True, json_schema_extra={"examples": [example]}),
        __module__=__name__,
        kind=(Literal[kind], ...),
        params=(params, ...),
        device=(JobDevice, Field("cpu", description="cpu: queue 'cpu'; gpu: queue 'gpu' (the job runs on CUDA)")),
    )


GenerateJobCreate = _job_create("generate", GenerateParams)
TrainJobCreate = _job_create("train", TrainParams, device="gpu")
EvaluateJobCreate = _job_create("evaluate", EvaluateParams)
BenchmarkJobCreate = _job_create("benchmark", BenchmarkParams)
InferJobCreate = _job_create("infer", InferParams)


# --- fit jobs (right-sizing, model.fit): the smallest preset of a family that meets a target -----------------

class FitParams(BaseModel):
    """Train (or reuse) a ladder of a learned family's presets, measure each on the validation split and in ms per
    frame, and register the smallest that meets the target with an alias (see README, Right-sizing)."""

    model_config = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False, json_schema_extra={"examples": [
        {"dataset": "rooms", "method": "wskpn", "presets": ["xs", "s", "m", "l"], "target": "psnr=30",
         "steps": 2000, "register_as": "wskpn-rooms-fit", "alias": "fitted"},
        {"dataset": "rooms", "method": "wskpn", "target": "ms=20@128x128", "steps": 2000, "threads": 2}]})

    dataset: str = Field(pattern=_ID_PATTERN)
    method: str = Field(min_length=1, max_length=100, pattern=r"^[A-Za-z0-9_]+$",
                        description="learned registry method family (no preset), e.g. wskpn")
    presets: list[str] | None = Field(None, min_length=1, max_length=32,
                                      description="presets on the ladder (none: the family's presets without a "
                                                  "variant suffix, e.g. xs, s, m, l)")
    target: str = Field(min_length=1, max_length=100,
                        description="psnr=DB (validation PSNR >= DB), flip=E (validation FLIP <= E), "
                                    "ms=MS[@WxH] (ms per frame <= MS at render size WxH, then the best PSNR), "
                                    "within=DB (PSNR >= the largest preset's - DB)")
    scale: Literal[1, 2] = Field(1, description="output / render resolution")
    steps: int = Field(1000, ge=1, le=10_000_000, description="training steps per preset")
    crop: int = Field(64, ge=1, le=4096, description="crop size in render pixels")
    batch: int = Field(4, ge=1, le=4096, description="batch size")
    frames_per_sample: int = Field(4, ge=1, le=256, description="consecutive frames unrolled per sample")
    lr: float = Field(1e-3, gt=0, le=10, description="Adam learning rate")
    warmup_steps: int = Field(50, ge=0, le=10_000_000)
    seed: int = Field(0, ge=0, le=2**31 - 1)
    train_split: JobSplit = "train"
    validation_split: JobSplit = Field("validation", description="where quality is measured (must not be empty)")
    validation_frames: int | None = Field(None, ge=1, le=100_000, description="frames per validation sequence "
                                                                              "measured (none: all)")
    time_at: list[int] = Field([256, 256], min_length=2, max_length=2,
                               description="[width, height] of the render frames timed when the target is not ms")
    timing_frames: int = Field(10, ge=1, le=10_000, description="frames timed per preset (after 3 warm-up frames)")
    threads: int | None = Field(None, ge=1, le=1024, description="torch threads for training, measuring, timing")
    register_as: str | None = Field(None, pattern=_ID_PATTERN,
                                    description="registered model name (none: FAMILY-fit-xSCALE)")
    _register_as_not_auto = _field_validator("register_as")(_registrable)
    alias: str = Field("fitted", pattern=r"^[A-Za-z_][A-Za-z0-9_-]{0,63}$",
                       description="alias set on the chosen version")
    experiment: str = Field("denoiser", min_length=1, max_length=200, description="MLflow experiment")
    track: bool = Field(True, description="log to MLflow, register versions and set the alias (false: only the "
                                          "ladder files in the job folder)")

    @_field_validator("time_at")
    @classmethod
    def _positive_size(cls, value: list[int]) -> list[int]:
        if not all(1 <= v <= 8192 for v in value):
            raise ValueError("time_at must be [width, height], each between 1 and 8192")
        return value


FitJobCreate = _job_create("fit", FitParams)


# POST /jobs body: the kind picks the parameter schema.
JobCreate = _Annotated[
    _Union[GenerateJobCreate, TrainJobCreate, EvaluateJobCreate, BenchmarkJobCreate, InferJobCreate, FitJobCreate],
    Field(discriminator="kind"),
]
JOB_PARAMS: dict[str, type[BaseModel]] = {"generate": GenerateParams, "train": TrainParams,
                                         "evaluate": EvaluateParams, "benchmark": BenchmarkParams,
                                         "infer": InferParams, "fit": FitParams}


class JobProgress(BaseModel):
    """Progress of the running execution (the same shape Celery's update_state carries)."""

    model_config = ConfigDict(json_schema_extra={"examples": [
        {"current": 120, "total": 2000, "message": "step 120/2000, loss 0.4210", "eta_seconds": 310.5}]})

    current: int = Field(description="units done (steps, frames, method-sequence runs)")
    total: int = Field(description="units in all; 0 until known")
    message: str
    eta_seconds: float | None = Field(description="estimated seconds left, from this execution's rate so far")


class JobErrorInfo(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"code": "invalid_input", "message": "ValueError: sequence 'a' is 8x8, smaller than the 64x64 crop"}]})

    code: str
    message: str


class Job(BaseModel):
    """A job: what was asked, where it runs, how far it got, and what came out."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "id": "5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e", "kind": "train", "state": "running",
        "params": {**TrainParams.model_config["json_schema_extra"]["examples"][0]},
        "device": "gpu", "queue": "gpu", "created_at": "2026-11-22T06:30:57.715000Z",
        "started_at": "2026-11-22T06:31:02.100000Z", "finished_at": None,
        "progress": {"current": 120, "total": 2000, "message": "step 120/2000, loss 0.4210", "eta_seconds": 310.5},
        "mlflow_run_id": "9a8b7c6d5e4f", "mlflow_url": "http://mlflow.local:5000/#/experiments/1/runs/9a8b7c6d5e4f",
        "result": None, "error": None, "attempts": 1, "cancel_requested": False}]})

    id: str
    kind: JobKind
    state: JobState
    params: dict[str, _Any] = Field(description="the parameters with every default filled in")
    device: JobDevice
    queue: str = Field(description="Celery queue the job was sent to")
    created_at: _datetime
    started_at: _datetime | None = Field(description="first start of an execution")
    finished_at: _datetime | None
    progress: JobProgress
    mlflow_run_id: str | None
    mlflow_url: str | None = Field(description="the run in the MLflow UI (when the server knows the UI's URL)")
    result: dict[str, _Any] | None = Field(description="kind-specific summary once the job succeeded")
    error: JobErrorInfo | None
    attempts: int = Field(description="executions started (more than 1 after a worker was lost and the job resumed)")
    cancel_requested: bool = Field(description="a cancel was asked; a running job stops at its next progress point")


class JobLogs(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"lines": [
        "2026-11-22 06:31:02,100 INFO denoiser.jobs.5f0c3a9e: attempt 1 of train job started on worker-1",
        "2026-11-22 06:31:12,301 INFO denoiser.jobs.5f0c3a9e: progress 40/2000, ETA 490 s: step 40/2000"]}]})

    lines: list[str] = Field(description="the last lines of the job's log, oldest first")


class ResultFrame(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"frame": "frame_0003.exr", "frame_index": 3, "bytes": 196_830,
         "url": "/jobs/5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e/results/kitchen_0/frame_0003.exr"}]})

    frame: str = Field(description="file name")
    frame_index: int
    bytes: int
    url: str


class ResultSequence(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"name": "kitchen_0", "frames": [
        ResultFrame.model_config["json_schema_extra"]["examples"][0]]}]})

    name: str
    frames: list[ResultFrame]


class JobResults(BaseModel):
    """Output frames of an infer job: one-part float32 R,G,B EXRs at the model's output resolution."""

    model_config = ConfigDict(json_schema_extra={"examples": [{
        "job_id": "5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e", "state": "succeeded", "complete": True,
        "zip_url": "/jobs/5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e/results.zip",
        "sequences": [ResultSequence.model_config["json_schema_extra"]["examples"][0]]}]})

    job_id: str
    state: JobState
    complete: bool = Field(description="the job succeeded: every frame is there")
    zip_url: str
    sequences: list[ResultSequence]
