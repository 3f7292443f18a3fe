"""Every MLflow call of the project: runs, metrics, sample grids, logged and registered models.

``MLflowTracker`` implements ``model.training.train.Tracker`` (the model library itself never imports MLflow). Only rank 0
of a training job creates one.

Where things go. The tracking URI is one setting: ``TrainConfig.tracking_uri`` when given, else the service's
(``core.settings.Settings.resolved_tracking_uri``: ``DENOISER_TRACKING_URI``, else the SQLite store under the data
folder), whatever the current folder. With a SQLite URI, artifacts go to ``artifacts/<experiment>/`` next to the
database file (MLflow would otherwise put them under the current folder of whichever process created the
experiment); a server or PostgreSQL URI keeps the server's artifact store.

Models. The final checkpoint (``model.training.checkpoint``, loadable with ``load_method``) is stored as an MLflow 3
*logged model* of the run in the ``pyfunc`` flavour (``core.pyfunc_model``: an MLmodel file with a signature,
the checkpoint inside as its artifact, its code and ``model/`` too, so ``mlflow.pyfunc.load_model`` denoises a
sequence without the project), with a copy of the checkpoint at the model's root (``checkpoint.pt``, what the service
downloads: it drives methods through ``step``), and registered as a new version from its run, tagged with method,
preset, scale, params, flops_per_pixel and validation PSNR (the measurements also as the run's metrics) and
described. ``download_registered_checkpoint`` brings a version's
checkpoint back. Aliases (not stages) mark versions for serving; choosing them is the service's business.

Lineage. Every run is tagged with the code version (``mlflow.source.git.commit`` and ``code_version``: the git
commit of the project, with ``+dirty`` when the working tree has uncommitted changes, else the package version),
and ``log_dataset`` records a dataset as a run input (``mlflow.log_input``): its name, path and digest (sha256 of
its manifests, ``model.io.dataset.dataset_digest``) with the context (training, evaluation).
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

# MLflow 3 sends usage telemetry by default; this service runs offline and must not phone home.
os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")

import mlflow  # noqa: E402  (after the telemetry switch)
from mlflow import MlflowClient  # noqa: E402
from mlflow.entities import (  # noqa: E402
    Dataset,
    DatasetInput,
    InputTag,
    LoggedModelOutput,
    LoggedModelStatus,
    Metric,
    Param,
    RunStatus,
)
from mlflow.exceptions import MlflowException  # noqa: E402

CHECKPOINT_ARTIFACT = "checkpoint.pt"
# Version tags that are measurements: each is also logged as a metric of the version's logged model.
MEASUREMENT_TAGS = ("validation_psnr", "validation_ssim", "ms_per_frame")
MEASUREMENT_TAG_PREFIX = "metric."
# How the pyfunc model is packed (tag ``pyfunc_layout``): "2" carries its code (core/pyfunc_model.py and model/).
PYFUNC_LAYOUT = "2"
PARAM_VALUE_LIMIT = 6000  # MLflow refuses longer parameter values
BATCH_LIMIT = 100  # params per log_batch call (MLflow's limit); metrics are flushed in batches of this size too


def resolve_tracking_uri(uri: str | None = None) -> str:
    """The tracking URI to use: ``uri``, else the settings' (``DENOISER_TRACKING_URI``, else under the data folder)."""
    from core.settings import get_settings

    return uri or get_settings().resolved_tracking_uri()


def sqlite_path(uri: str) -> Path | None:
    """The database file of a ``sqlite:///`` URI, None for other backends."""
    prefix = "sqlite:///"
    return Path(uri[len(prefix):]) if uri.startswith(prefix) else None


def _slug(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "experiment"


class MLflowTracker:
    """Logs one training run to MLflow (see the module notes for where everything goes).

    Metrics are buffered and written in batches (``flush_every`` values, and before images, models and the
    end of the run): one SQLite transaction per step would cost more than a tiny model's training step.
    """

    def __init__(self, tracking_uri: str | None = None, experiment: str = "denoiser", flush_every: int = BATCH_LIMIT,
                 run_name: str | None = None) -> None:
        self.tracking_uri = resolve_tracking_uri(tracking_uri)
        self.experiment = experiment
        self.flush_every = flush_every
        self.run_name = run_name
        self._client: MlflowClient | None = None
        self._run_id: str | None = None
        self._experiment_id: str | None = None
        self._pending: list[Metric] = []

    @property
    def run_id(self) -> str | None:
        return self._run_id

    @property
    def client(self) -> MlflowClient:
        if self._client is None:
            database = sqlite_path(self.tracking_uri)
            if database is None:
                self._client = MlflowClient(self.tracking_uri, registry_uri=self.tracking_uri)
                return self._client
            database.parent.mkdir(parents=True, exist_ok=True)  # SQLite creates the file, not its folder
            # MLflow creates and migrates its tables when a client first opens the store, unguarded: two jobs
            # starting together on a new database race ("duplicate column name"). One process at a time opens it.
            with open(database.with_name(database.name + ".lock"), "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)
                client = MlflowClient(self.tracking_uri, registry_uri=self.tracking_uri)
                client.search_experiments(max_results=1)
                client.search_registered_models(max_results=1)
            self._client = client
        return self._client

    # ------------------------------------------------------------------------------------ run

    def start(self, params: dict[str, Any], resume_run_id: str | None = None) -> None:
        self._experiment_id = self._experiment_id_for(self.experiment)
        logged: dict[str, str] = {}
        if resume_run_id is not None and self._resumable(resume_run_id):
            self._run_id = resume_run_id
            self.client.update_run(resume_run_id, status=RunStatus.to_string(RunStatus.RUNNING))
            logged = self.client.get_run(resume_run_id).data.params
        else:
            run_name = self.run_name or f"{params.get('method', 'train')}"
            self._run_id = self.client.create_run(self._experiment_id, run_name=run_name).info.run_id
        for key, value in code_version_tags().items():
            self.client.set_tag(self._run_id, key, value)
        values = {key: str(value)[:PARAM_VALUE_LIMIT] for key, value in params.items()}
        # A resumed run keeps its parameters (MLflow never changes one); a changed setting becomes a tag.
        new = [Param(key, value) for key, value in values.items() if key not in logged]
        for start in range(0, len(new), BATCH_LIMIT):
            self.client.log_batch(self._run_id, params=new[start:start + BATCH_LIMIT])
        for key, value in values.items():
            if key in logged and logged[key] != value:
                self.client.set_tag(self._run_id, f"resumed_with.{key}", value)

    def _experiment_id_for(self, name: str) -> str:
        existing = self.client.get_experiment_by_name(name)
        if existing is not None:
            return existing.experiment_id
        database = sqlite_path(self.tracking_uri)
        location = None if database is None else (database.parent / "artifacts" / _slug(name)).as_uri()
        try:
            return self.client.create_experiment(name, artifact_location=location)
        except MlflowException:  # another process created it meanwhile
            existing = self.client.get_experiment_by_name(name)
            if existing is None:
                raise
            return existing.experiment_id

    def _resumable(self, run_id: str) -> bool:
        try:
            run = self.client.get_run(run_id)
        except MlflowException:
            return False  # a checkpoint from another tracking store: start a new run
        return run.info.experiment_id == self._experiment_id

    def finish(self, status: str) -> None:
        if self._run_id is None:
            return
        self._flush()
        self.client.set_terminated(self._run_id, status=status)

    # -------------------------------------------------------------------------------- logging

    def log_metrics(self, metrics: dict[str, float], step: int) -> None:
        timestamp = int(time.time() * 1000)
        self._pending.extend(Metric(key, float(value), timestamp, step) for key, value in metrics.items())
        if len(self._pending) >= self.flush_every:
            self._flush()

    def _flush(self) -> None:
        while self._pending:
            batch, self._pending = self._pending[:BATCH_LIMIT], self._pending[BATCH_LIMIT:]
            self.client.log_batch(self._run_id, metrics=batch)

    def log_image_grid(self, name: str, columns: dict[str, list[np.ndarray]], step: int) -> None:
        self._flush()
        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / Path(name).name
            save_image_grid(columns, path, title=f"step {step}")
            artifact_folder = str(Path(name).parent) if Path(name).parent != Path(".") else None
            self.client.log_artifact(self._run_id, str(path), artifact_folder)

    def log_dataset(self, path: str | os.PathLike, context: str) -> None:
        """Record a dataset folder as an input of the run (``mlflow.log_input``): name, path, manifests' digest."""
        from model.io.dataset import dataset_digest

        root = Path(path).resolve()
        dataset = Dataset(name=root.name, digest=dataset_digest(root)[:36], source_type="local",
                          source=root.as_uri())
        self.client.log_inputs(self._run_id, datasets=[DatasetInput(dataset, [InputTag("mlflow.data.context",
                                                                                       context)])])

    def log_model(self, checkpoint: Path, registered_name: str, tags: dict[str, str],
                  description: str | None = None) -> dict[str, Any]:
        """Store ``checkpoint`` as the run's logged model (pyfunc flavour, see the module notes) and register it as a
        new version of ``registered_name`` with ``description`` (else one written from the tags). The tags that are
        measurements (``validation_psnr``, ``metric.NAME``, ...) are also logged as metrics of the run linked to the
        model, so MLflow shows them as the version's metrics."""
        self._flush()
        tags = {**tags, "pyfunc_layout": PYFUNC_LAYOUT}
        for key, value in tags.items():
            self.client.set_tag(self._run_id, key, value)
        model = self.client.create_logged_model(self._experiment_id, name=_slug(registered_name),
                                                source_run_id=self._run_id, tags=tags)
        # What mlflow.pyfunc.log_model does inside a run: the run lists the model among its outputs.
        self.client.log_outputs(self._run_id, [LoggedModelOutput(model.model_id, step=0)])
        with tempfile.TemporaryDirectory() as folder:
            save_pyfunc_model(checkpoint, Path(folder) / "model", run_id=self._run_id, model_id=model.model_id)
            self.client.log_model_artifacts(model.model_id, str(Path(folder) / "model"))
        measured = measurement_metrics(tags)
        if measured:
            timestamp = int(time.time() * 1000)
            self.client.log_batch(self._run_id, metrics=[Metric(key, value, timestamp, 0, model_id=model.model_id)
                                                         for key, value in measured.items()])
        self.client.finalize_logged_model(model.model_id, LoggedModelStatus.READY)
        try:
            self.client.create_registered_model(registered_name)
        except MlflowException as error:
            if error.error_code not in ("RESOURCE_ALREADY_EXISTS", "ALREADY_EXISTS"):
                raise
        # The source is the logged model's artifact folder rather than "models:/<id>": MLflow's SQL registry
        # resolves "models:/" through the process-wide tracking URI, not this client's.
        version = self.client.create_model_version(registered_name, source=model.artifact_location,
                                                   run_id=self._run_id, tags=tags, model_id=model.model_id,
                                                   description=description or version_description(tags))
        return {"name": registered_name, "version": str(version.version), "model_id": model.model_id,
                "uri": f"models:/{registered_name}/{version.version}"}


def measurement_metrics(tags: dict[str, str]) -> dict[str, float]:
    """The numbers among version tags, named as metrics: ``validation_psnr`` as is, ``metric.held_out_psnr`` as
    ``held_out_psnr``."""
    metrics = {}
    for key, value in tags.items():
        if key in MEASUREMENT_TAGS or key.startswith(MEASUREMENT_TAG_PREFIX):
            try:
                metrics[key.removeprefix(MEASUREMENT_TAG_PREFIX)] = float(value)
            except ValueError:
                continue
    return metrics


def version_description(tags: dict[str, str]) -> str:
    """A version's description from its tags: method, preset, scale, size and how to load it."""
    label = f"{tags.get('method', 'a denoiser')}" + (f":{tags['preset']}" if tags.get("preset") else "")
    size = ", ".join(part for part in (f"{tags['params']} parameters" if tags.get("params") else "",
                                       f"{tags['flops_per_pixel']} FLOPs per pixel" if tags.get("flops_per_pixel")
                                       else "") if part)
    lines = [f"{label} at scale {tags.get('scale', '?')}" + (f" ({size})" if size else "") + "."]
    if tags.get("validation_psnr"):
        lines.append(f"Validation PSNR {float(tags['validation_psnr']):.2f} dB.")
    lines.append("A pyfunc model (`mlflow.pyfunc.load_model`): one sequence of frame buffers in, RGB frames out; "
                 "`checkpoint.pt` at the model's root is the checkpoint the service runs.")
    return "\n\n".join(lines)


def download_registered_checkpoint(name: str, version: str | int, destination: str | os.PathLike,
                                   tracking_uri: str | None = None) -> Path:
    """Fetch the checkpoint of registered model ``name`` version ``version`` into ``destination``; returns its path."""
    uri = resolve_tracking_uri(tracking_uri)
    client = MlflowClient(uri, registry_uri=uri)
    location = client.get_model_version_download_uri(name, str(version))
    destination = Path(destination)
    destination.mkdir(parents=True, exist_ok=True)
    local = mlflow.artifacts.download_artifacts(artifact_uri=f"{location}/{CHECKPOINT_ARTIFACT}",
                                                dst_path=str(destination), tracking_uri=uri)
    return Path(local)


def save_image_grid(columns: dict[str, list[np.ndarray]], path: str | os.PathLike, title: str | None = None) -> Path:
    """A PNG with one column per entry of ``columns`` (title -> HxWx3 images in [0, 1]) and one row per sample."""
    # A bare Figure (no pyplot): no global backend or figure registry touched, safe in workers and threads.
    from matplotlib.figure import Figure

    names = list(columns)
    rows = min((len(images) for images in columns.values()), default=0)
    if rows == 0:
        raise ValueError("an image grid needs at least one column with one image")
    figure = Figure(figsize=(2.2 * len(names), 2.2 * rows + 0.4))
    axes = figure.subplots(rows, len(names), squeeze=False)
    for column, name in enumerate(names):
        for row in range(rows):
            axis = axes[row][column]
            axis.imshow(np.clip(columns[name][row], 0.0, 1.0), interpolation="nearest")
            axis.set_xticks([])
            axis.set_yticks([])
            if row == 0:
                axis.set_title(name, fontsize=10)
    if title:
        figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    path = Path(path)
    figure.savefig(path, dpi=100)
    return path


PRETRAINED_ALIAS = "pretrained"
PRETRAINED_EXPERIMENT = "pretrained"


def pretrained_tags(model) -> dict[str, str]:
    """Version tags of a shipped model (``model.deployment.pretrained.PretrainedModel``): what training tags, its sha256, and
    its held-out PSNR / FLIP with OIDN-high's of the same evaluation run when measured."""
    manifest, training = model.manifest, model.manifest.get("training") or {}
    tags = {"method": model.method, "preset": model.preset, "scale": str(model.scale),
            "params": str(manifest.get("params", "")), "flops_per_pixel": str(manifest.get("flops_per_pixel", "")),
            "sha256": model.sha256, "pretrained": "true", "held_out": model.held_out.get("status", "pending"),
            "steps": str(training.get("step", ""))}
    best = training.get("best_metric") or {}
    if best.get("name") == "validation/psnr" and best.get("value") is not None:
        tags["validation_psnr"] = f"{best['value']:.4f}"
    row = model.held_out_row()
    if row is not None:
        for key in ("psnr", "flip"):
            if row.get(key) is not None:
                tags[f"metric.held_out_{key}"] = f"{row[key]:.6g}"
        for peer in model.held_out.get("peers") or []:
            if peer.get("label") == "oidn:high" and peer.get("psnr") is not None:
                tags["metric.held_out_oidn_high_psnr"] = f"{peer['psnr']:.6g}"
    return {key: value for key, value in tags.items() if value != ""}


def pretrained_description(model) -> str:
    """A shipped model's version description: method, scale, size, what it was trained on, its held-out table."""
    from model.deployment.pretrained import held_out_markdown

    manifest, training = model.manifest, model.manifest.get("training") or {}
    dataset = training.get("dataset") or {}
    size = ", ".join(part for part in (f"{manifest['params']} parameters" if manifest.get("params") else "",
                                       f"{manifest['flops_per_pixel']:.4g} FLOPs per pixel"
                                       if manifest.get("flops_per_pixel") else "") if part)
    lines = [f"Pretrained `{model.name}`, shipped with the project: {model.method}:{model.preset} at scale "
             f"{model.scale}" + (f" ({size})" if size else "") + f"; weights sha256 `{model.sha256[:16]}…`."]
    trained = f"Trained {training.get('step', '?')} steps"
    if dataset.get("path"):
        trained += f" on `{dataset['path']}`" + (f" (made by `{dataset['script']}`)" if dataset.get("script") else "")
        scenes = ((dataset.get("splits") or {}).get("train") or {}).get("scenes") or []
        if scenes:
            trained += f", scenes {', '.join(scenes)}"
    best = training.get("best_metric") or {}
    if best.get("value") is not None:
        trained += f"; best {best.get('name', 'validation')} {best['value']:.2f}"
    lines.append(trained + ".")
    if manifest.get("note"):
        lines.append(manifest["note"])
    held_out = model.held_out
    if held_out.get("status") == "measured":
        where = ", ".join(part for part in (f"{held_out.get('split')} split" if held_out.get("split") else "",
                                            f"{len(held_out.get('sequences') or [])} sequences",
                                            f"{held_out.get('device')}" if held_out.get("device") else "",
                                            f"report `{held_out['report']}`" if held_out.get("report") else "")
                          if part)
        lines.append(f"Held-out evaluation ({where}), next to OIDN of the same run:\n\n{held_out_markdown([model])}")
    else:
        lines.append("Held-out evaluation pending.")
    return "\n\n".join(lines)


def register_pretrained(model, tracking_uri: str | None = None, alias: str = PRETRAINED_ALIAS) -> dict[str, Any]:
    """Register a shipped model once and point ``alias`` at it: a version of ``model.name`` tagged with the same
    sha256 and pyfunc layout is reused (so running this again changes nothing), else the file is checked and logged
    as a new version from a run of the ``pretrained`` experiment, with its held-out scores as metrics and a
    description. Returns name, version, uri and whether it was created."""
    from model.deployment.pretrained import verify

    tracker = MLflowTracker(tracking_uri, experiment=PRETRAINED_EXPERIMENT, run_name=model.name)
    client = tracker.client
    if "'" in model.name:
        raise ValueError(f"model name {model.name!r} contains a quote")
    same = [version for version in client.search_model_versions(f"name = '{model.name}'")
            if (version.tags or {}).get("sha256") == model.sha256
            and (version.tags or {}).get("pyfunc_layout") == PYFUNC_LAYOUT]
    created = not same
    if same:
        version = str(min(int(v.version) for v in same))
    else:
        path = verify(model)
        training = model.manifest.get("training") or {}
        dataset = training.get("dataset") or {}
        tracker.start({"method": f"{model.method}:{model.preset}", "scale": model.scale, "pretrained": model.name,
                       "sha256": model.sha256, "steps": training.get("steps"), "step": training.get("step"),
                       "seed": training.get("seed"), "training_script": training.get("script"),
                       "dataset_script": dataset.get("script"), "dataset_digest": dataset.get("digest")})
        try:
            version = tracker.log_model(path, model.name, pretrained_tags(model),
                                        description=pretrained_description(model))["version"]
        except BaseException:
            tracker.finish("FAILED")
            raise
        tracker.finish("FINISHED")
    client.set_registered_model_alias(model.name, alias, version)
    if not client.get_registered_model(model.name).description:
        client.update_registered_model(model.name, description=(
            f"{model.method}:{model.preset} at scale {model.scale}, shipped with the project (pretrained/{model.name}); "
            f"alias `{alias}` marks the registered copy of the shipped weights."
            + (f" {model.manifest['note']}" if model.manifest.get("note") else "")))
    return {"name": model.name, "version": version, "uri": f"models:/{model.name}@{alias}", "created": created}


def save_pyfunc_model(checkpoint: str | os.PathLike, folder: Path, run_id: str | None = None,
                      model_id: str | None = None) -> Path:
    """Write ``checkpoint`` as a pyfunc model into ``folder`` (MLmodel, signature, the checkpoint as its artifact) plus
    a copy at ``folder/checkpoint.pt``. Self-contained: the wrapper (``core/pyfunc_model.py``, as the model's code)
    and the library ``model/`` (a code path, without bytecode) go inside, so it loads wherever its requirements,
    pinned to this environment's torch, numpy and MLflow, are installed, the project not needed."""
    import numpy
    import torch

    import core.pyfunc_model as wrapper
    import model as library
    from mlflow.models import Model

    with tempfile.TemporaryDirectory() as staging:
        code = Path(staging) / "model"
        shutil.copytree(Path(library.__file__).parent, code,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.pt", "*.onnx"))
        mlflow.pyfunc.save_model(str(folder), python_model=wrapper.__file__,
                                 artifacts={wrapper.CHECKPOINT_KEY: str(checkpoint)}, code_paths=[str(code)],
                                 signature=wrapper.signature(), mlflow_model=Model(run_id=run_id, model_id=model_id),
                                 pip_requirements=[f"torch=={torch.__version__.split('+')[0]}",
                                                   f"numpy=={numpy.__version__}", f"mlflow=={mlflow.__version__}"])
    shutil.copy2(checkpoint, folder / CHECKPOINT_ARTIFACT)
    return folder


_CODE_VERSION: dict[str, str] | None = None


def code_version_tags() -> dict[str, str]:
    """``mlflow.source.git.commit`` (when the project is a git checkout) and ``code_version`` (the commit, with
    ``+dirty`` for uncommitted changes, else the installed package's version), read once per process."""
    global _CODE_VERSION
    if _CODE_VERSION is None:
        root = Path(__file__).resolve().parent.parent
        tags: dict[str, str] = {}
        try:
            commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                    timeout=10, check=True).stdout.strip()
            dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                   capture_output=True, text=True, timeout=10, check=True).stdout.strip()
            tags = {"mlflow.source.git.commit": commit, "code_version": commit + ("+dirty" if dirty else "")}
        except (OSError, subprocess.SubprocessError):
            from importlib.metadata import PackageNotFoundError, version

            try:
                tags = {"code_version": f"denoiser-service {version('denoiser-service')}"}
            except PackageNotFoundError:
                tags = {"code_version": "unknown"}
        _CODE_VERSION = tags
    return dict(_CODE_VERSION)
