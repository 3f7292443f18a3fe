"""The one settings object of the API, the workers and the CLI, read from DENOISER_* environment variables."""

from __future__ import annotations

import os
from functools import lru_cache
from typing import Literal
from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

# The folder holding core/: a source checkout when pyproject.toml sits beside it, else an installed package's
# site-packages (where nothing may be written).
PROJECT_ROOT = Path(__file__).resolve().parents[1]
SQLITE_PREFIX = "sqlite:///"


def default_data_dir() -> Path:
    """``var/`` of the checkout the code runs from, else the per-user ``$XDG_DATA_HOME/denoiser``
    (``~/.local/share/denoiser``): the same folder whatever the current one is."""
    if (PROJECT_ROOT / "pyproject.toml").is_file():
        return PROJECT_ROOT / "var"
    base = os.environ.get("XDG_DATA_HOME", "")
    return (Path(base) if os.path.isabs(base) else Path.home() / ".local" / "share") / "denoiser"


class Settings(BaseSettings):
    """Every knob of the API, the workers and the CLI. Environment: DENOISER_<FIELD> (e.g. DENOISER_API_KEY).

    docs/operations.md ("Where things are stored") describes how the paths resolve.
    """

    model_config = SettingsConfigDict(env_prefix="DENOISER_", extra="ignore")

    data_dir: Path = Field(
        default_factory=default_data_dir,
        description="root of everything the service stores: datasets, jobs, results, the model cache and (with no "
                    "tracking_uri) the MLflow store; default: var/ of the source checkout the code runs from, else "
                    "~/.local/share/denoiser ($XDG_DATA_HOME/denoiser); a relative path is taken from the current "
                    "folder once, when the settings are read")
    redis_url: str = Field("redis://127.0.0.1:6379/0", description="Celery broker, result backend, session mirror")
    tracking_uri: str | None = Field(
        None, description="MLflow tracking and registry URI of the service, the workers and every CLI command; "
                          "none: the SQLite store data_dir/mlflow/mlflow.db (a relative sqlite:/// path is taken "
                          "from the current folder once)")
    pretrained_dir: Path | None = Field(
        None, description="folder of the shipped pretrained models (one folder per model, a manifest.json each); "
                          "none: pretrained/ of the source checkout (an installed package needs it set)")
    mlflow_ui_url: str | None = Field(None, description="public URL of the MLflow UI, for links in job records")
    url: str = Field("http://127.0.0.1:8000",
                     description="address of the REST service that the CLI's client commands talk to (--url)")
    api_key: str | None = Field(None, description="when set, every request but /health needs X-API-Key; the CLI's "
                                                  "client commands send it (--api-key)")
    require_api_key: bool = Field(
        False, description="refuse to start without a real api_key (set where the API is reachable from other "
                           "machines; `denoiser serve --host` beyond localhost implies it)")
    public_api_docs: bool = Field(
        False, description="/openapi.json, /docs and /redoc answer without the API key (they need it by default "
                           "when api_key is set)")
    max_upload_bytes: int = Field(2 * 1024**3, gt=0, description="largest accepted dataset upload")
    max_frame_bytes: int = Field(256 * 1024**2, gt=0, description="largest accepted single-frame EXR")
    max_frame_pixels: int = Field(
        2 * 1024**2, gt=0, description="largest render resolution (width x height) of any frame (sessions, frame "
        "uploads, archives, in any layout), checked from the EXR headers before decoding; all parts together may "
        "declare 128 values (pixels x channels) per pixel of it")
    max_unpacked_bytes: int = Field(4 * 1024**3, gt=0, description="most bytes one archive may unpack to")
    max_archive_ratio: float = Field(
        20.0, gt=0, description="most bytes an archive may unpack to per byte uploaded, once past "
        "archive_ratio_exempt_bytes (frame EXRs barely compress further; a zip bomb compresses 1000:1)")
    archive_ratio_exempt_bytes: int = Field(
        16 * 1024**2, ge=0, description="unpacked bytes any archive may have whatever its ratio (tiny uploads)")
    max_concurrent_uploads: int = Field(2, gt=0, description="dataset uploads (archives and frames) received or "
                                                             "unpacked at once; one more answers 429")
    max_decoded_frame_bytes: int = Field(
        512 * 1024**2, gt=0, description="most bytes decoding one frame EXR may take (all its parts and channels, "
        "4 bytes a value), checked from the headers before decoding (session frames, frame uploads, archives' EXRs); past it 413")
    max_buffered_frame_bytes: int = Field(
        1024**3, gt=0, description="bytes of session frame bodies held in memory at once (each from its first byte "
                                   "until its output is encoded); a frame past it answers 503 (retry)")
    body_read_timeout_seconds: float = Field(
        30.0, gt=0, description="longest wait for the next chunk of a request body (frames and uploads): 408 after")
    staged_upload_ttl_seconds: int = Field(
        24 * 3600, gt=0, description="frame-by-frame uploads untouched this long are discarded")
    session_owner_tokens: bool = Field(
        False, description="sessions answer only to the X-Session-Token returned when they were created")
    session_ttl_seconds: int = Field(1800, gt=0, description="idle time after which a session expires")
    max_sessions: int = Field(16, gt=0, description="live sessions; one more answers 429")
    session_device: str = Field("cpu", description="torch device sessions run on")
    session_workers: int = Field(
        2, gt=0, description="threads that run session frames (each its own torch thread team): one slow session "
                             "holds one of them while the others serve the rest")
    session_threads: int | None = Field(
        None, gt=0, description="torch threads of each session worker; none: the cores shared out among them")
    job_threads: int | None = Field(
        None, gt=0, description="torch threads of a job in a worker (training, evaluation, inference; DDP ranks "
                                "share them); none: torch's default, every core")
    session_mirror_interval_seconds: float = Field(
        0.0, ge=0, le=3600, description="0: every frame's history is in Redis before the next frame runs; > 0: "
        "written at most this often (large histories, GPU sessions), so a restart may resume that far back")
    session_history_precision: Literal["half", "float"] = Field(
        "half", description="how a session's history is kept in Redis: half (float16 where the values fit, about "
        "half the bytes; a restored session's outputs differ by float16 rounding) or float (exact)")
    inference_forms: str = Field(
        "measured", min_length=1, description="how learned methods' networks run on the CPU: measured (the form "
        "table shipped in model/deployment/inference_forms.json: channels_last and/or bf16 where they measured faster per method "
        "and resolution), off (fp32 eager everywhere), or the path of a table written by "
        "scripts/bench_inference_forms.py")
    native_kernels: bool = Field(
        True, description="the fused models' CPU steps run hand-written C kernels for their passes around the "
        "network (model/ops/native: compiled with the machine's C compiler on first use; the same outputs to float "
        "rounding); false: torch's ops everywhere")
    native_cache_dir: Path | None = Field(
        None, description="where compiled native kernels are kept, one file per source, compiler flags and CPU "
        "(default: data_dir/native-kernels)")
    worker_heartbeat_seconds: float = Field(
        10.0, gt=0, description="how often each worker writes its heartbeat; one silent for 3 times this is gone")
    redis_retry_seconds: float = Field(
        20.0, ge=0, description="how long a running job retries Redis (with backoff) before its attempt fails")
    job_time_limit_seconds: int = Field(24 * 3600, gt=0, description="longest job; the visibility timeout exceeds it")
    max_train_nodes: int = Field(8, ge=1, le=64, description="most nodes (workers of its queue) one train job may "
                                 "ask for")
    node_host: str | None = Field(None, description="address other nodes reach this worker's training rendezvous "
                                  "at (a multi-node job's first node publishes it); none: this machine's hostname's "
                                  "IP address, or its default route's when that is a loopback one")
    rendezvous_timeout_seconds: int = Field(600, gt=0, description="how long a multi-node job's nodes wait for each "
                                            "other (at the start and after a node is lost) before the job fails")
    collective_timeout_seconds: int = Field(1800, gt=0, description="how long a DDP rank waits in one collective "
                                            "(init_process_group timeout) before it fails: longer than rank 0's "
                                            "validation, which the other ranks wait out")
    node_max_restarts: int = Field(3, ge=0, le=100, description="times a multi-node job's ranks are restarted "
                                   "(torchrun --max-restarts) and a lost node replaced before the job fails")

    @field_validator("data_dir", "pretrained_dir")
    @classmethod
    def _absolute_path(cls, value: Path | None) -> Path | None:
        return None if value is None else Path(os.path.abspath(value.expanduser()))

    @field_validator("tracking_uri")
    @classmethod
    def _absolute_sqlite(cls, value: str | None) -> str | None:
        if not value:
            return None
        if value.startswith(SQLITE_PREFIX) and not os.path.isabs(value[len(SQLITE_PREFIX):]):
            return SQLITE_PREFIX + os.path.abspath(value[len(SQLITE_PREFIX):])
        return value

    def resolved_tracking_uri(self) -> str:
        if self.tracking_uri:
            return self.tracking_uri
        return f"{SQLITE_PREFIX}{(self.data_dir / 'mlflow' / 'mlflow.db').resolve()}"


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    settings = Settings()
    apply_to_model(settings)
    return settings


def apply_to_model(settings: Settings) -> None:
    """The model library's process-wide switches from the settings (every process reads its settings first)."""
    from core.storage import Storage
    from model.ops import native

    native.configure(settings.native_kernels, settings.native_cache_dir or Storage(settings.data_dir).native_kernels)
