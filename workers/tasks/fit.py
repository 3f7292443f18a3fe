"""The ``fit`` job (right-sizing, ``model.fit``) and the MLflow side of every fit, the CLI's included.

``MLflowFit`` implements ``model.fit.LadderTracker`` (one parent run per fit: per-preset params and metrics,
``ladder.json`` and ``ladder.md`` as artifacts) and ``model.fit.ModelStore`` (model versions: found by tags or by
run, downloaded, registered from the parent run, tagged, aliased); ``train_tracker(preset)`` gives each preset's
training its own run, a child of the parent (tag ``mlflow.parentRunId``).

The job trains into ``jobs/<id>/fit/<preset>-<key>/`` (an execution that follows a lost worker resumes there),
writes ``ladder.json`` and ``ladder.md`` into the job folder, and ends ``succeeded`` with the ladder in its result,
or ``failed`` with code ``target_not_met`` when no preset meets the target (the ladder files are written anyway).
Cancellation: the progress callback of every training step and measurement raises ``JobCancelled``.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from pathlib import Path
from typing import Any

from service.errors import ApiError
from service.schemas import FitParams, TrainParams
from service.settings import Settings
from service.storage import Storage
from workers.tasks.checks import invalid, open_dataset, split_sequences
from workers.tasks.context import JobContext, JobFailure

FIT_FOLDER = "fit"


# ------------------------------------------------------------------------------------------------- MLflow

class MLflowFit:
    """The fit's parent run and the registry calls of ``model.fit`` (see the module notes)."""

    def __init__(self, tracking_uri: str | None, experiment: str, run_name: str) -> None:
        from workers.tracking import MLflowTracker

        self.run = MLflowTracker(tracking_uri, experiment, run_name=run_name)
        self.tracking_uri = self.run.tracking_uri
        self.experiment = experiment
        self.run_name = run_name
        self._logged: set[str] = set()

    @property
    def client(self):
        return self.run.client

    @property
    def run_id(self) -> str | None:
        return self.run.run_id

    @property
    def experiment_id(self) -> str | None:
        return getattr(self.run, "_experiment_id", None)

    def start(self, params: dict[str, Any]) -> None:
        self.run.start(params)
        self._logged.update(params)
        self.client.set_tag(self.run_id, "kind", "fit")

    def finish(self, status: str) -> None:
        self.run.finish(status)

    # -- LadderTracker
    def log_params(self, params: dict[str, Any]) -> None:
        from mlflow.entities import Param

        from workers.tracking import PARAM_VALUE_LIMIT

        new = [Param(key, str(value)[:PARAM_VALUE_LIMIT]) for key, value in params.items() if key not in self._logged]
        self._logged.update(params)
        if new:
            self.client.log_batch(self.run_id, params=new)

    def log_metrics(self, metrics: dict[str, float], step: int) -> None:
        self.run.log_metrics(metrics, step)

    def log_text(self, name: str, text: str) -> None:
        self.run._flush()
        self.client.log_text(self.run_id, text, name)

    # -- training runs
    def train_tracker(self, preset: str):
        """A tracker for one preset's training: its own run, marked as a child of the fit's run."""
        from workers.tracking import MLflowTracker

        parent = self.run_id
        outer = self

        class _Child(MLflowTracker):
            def start(self, params: dict[str, Any], resume_run_id: str | None = None) -> None:
                super().start(params, resume_run_id)
                if parent:
                    self.client.set_tag(self.run_id, "mlflow.parentRunId", parent)

        return _Child(outer.tracking_uri, outer.experiment, run_name=f"{preset}: {outer.run_name}")

    # -- ModelStore
    @staticmethod
    def _version(entity) -> dict[str, Any]:
        return {"name": entity.name, "version": str(entity.version), "run_id": entity.run_id or None,
                "uri": f"models:/{entity.name}/{entity.version}"}

    def _search(self, filter_string: str) -> list:
        versions, token = [], None
        while True:
            page = self.client.search_model_versions(filter_string, max_results=1000, page_token=token)
            versions.extend(page)
            token = page.token
            if not token:
                return versions

    def find_version(self, tags: dict[str, str]) -> dict[str, Any] | None:
        key = tags.get("fit_key")
        if key is None or not key.isalnum():
            raise ValueError("find_version needs the fit_key tag (hexadecimal)")
        matches = [v for v in self._search(f"tags.fit_key = '{key}'")
                   if all((v.tags or {}).get(name) == value for name, value in tags.items())]
        if not matches:
            return None
        newest = max(matches, key=lambda v: (v.creation_timestamp or 0, int(v.version)))
        return self._version(newest)

    def version_of_run(self, run_id: str) -> dict[str, Any] | None:
        if not run_id or not run_id.isalnum():
            return None
        versions = self._search(f"run_id = '{run_id}'")
        if not versions:
            return None
        return self._version(max(versions, key=lambda v: (v.creation_timestamp or 0, int(v.version))))

    def download(self, version: dict[str, Any], folder: Path) -> Path:
        from workers.tracking import CHECKPOINT_ARTIFACT, download_registered_checkpoint

        folder = Path(folder)
        target = folder / CHECKPOINT_ARTIFACT
        with tempfile.TemporaryDirectory(dir=folder.parent if folder.parent.is_dir() else None) as staging:
            path = download_registered_checkpoint(version["name"], version["version"], staging, self.tracking_uri)
            folder.mkdir(parents=True, exist_ok=True)
            shutil.move(str(path), target)
        return target

    def register(self, checkpoint: Path, name: str, tags: dict[str, str]) -> dict[str, Any]:
        return self.run.log_model(Path(checkpoint), name, tags)

    def tag_version(self, version: dict[str, Any], tags: dict[str, str]) -> None:
        for key, value in tags.items():
            self.client.set_model_version_tag(version["name"], str(version["version"]), key, value)

    def set_alias(self, name: str, alias: str, version: str) -> None:
        self.client.set_registered_model_alias(name, alias, str(version))


def start_fit_run(config, tracking_uri: str | None, run_name: str) -> MLflowFit:
    """The parent run of a fit, started with the fit's settings as parameters."""
    recorder = MLflowFit(tracking_uri, config.experiment, run_name)
    recorder.start({"kind": "fit", "method": config.family, "steps": config.steps, "crop_size": config.crop_size,
                    "batch_size": config.batch_size, "frames_per_sample": config.frames_per_sample,
                    "lr": config.lr, "seed": config.seed, "validation_split": config.validation_split,
                    "validation_frames": config.validation_frames})
    return recorder


# -------------------------------------------------------------------------------------------------- the job

def fit_config(params: FitParams, storage: Storage, settings: Settings, out: Path, device: str):
    from model.fit import FitConfig

    return FitConfig(
        family=params.method, data=str(storage.dataset(params.dataset)), target=params.target,
        presets=params.presets, scale=params.scale, steps=params.steps, crop_size=params.crop,
        frames_per_sample=params.frames_per_sample, batch_size=params.batch, lr=params.lr,
        warmup_steps=params.warmup_steps, seed=params.seed, train_split=params.train_split,
        validation_split=params.validation_split, validation_frames=params.validation_frames,
        time_at=tuple(params.time_at), timing_frames=params.timing_frames, threads=params.threads, device=device,
        out=str(out), register_as=params.register_as, alias=params.alias,
        tracking_uri=settings.resolved_tracking_uri(), experiment=params.experiment)


def check(params: FitParams, storage: Storage, settings: Settings) -> dict[str, Any]:
    """The family, presets, target and data, checked from manifests (no frame decoded, nothing trained)."""
    from model.fit import Target, default_presets
    from model.methods.registry import method_spec
    from workers.tasks import train as train_kind
    from workers.tasks.methods import check_registry_method

    if ":" in params.method:
        raise ApiError(422, "invalid_params", f"method takes a family (e.g. wskpn), not a preset: "
                       f"{params.method!r}; choose presets with 'presets'")
    check_registry_method(params.method, params.scale, learned=True)
    presets = list(dict.fromkeys(params.presets)) if params.presets else default_presets(params.method)
    known = method_spec(params.method).presets
    unknown = [p for p in presets if p not in known]
    if unknown:
        raise ApiError(422, "unknown_preset", f"method {params.method!r} has no preset {unknown[0]!r}; presets: "
                       f"{', '.join(known)}")
    try:
        Target.parse(params.target, tuple(params.time_at))
    except ValueError as error:
        raise invalid(error, "invalid_target") from None
    if params.alias == "latest" or re.fullmatch(r"v\d+", params.alias):
        raise ApiError(422, "invalid_params", f"alias {params.alias!r} is reserved by MLflow ('latest', 'vN')")
    dataset = open_dataset(storage, params.dataset)
    split_sequences(dataset, params.dataset, params.validation_split, params.scale)
    # The training settings and data, checked as a train job of the first preset would be.
    train_kind.check(TrainParams(
        dataset=params.dataset, method=f"{params.method}:{presets[0]}", scale=params.scale, steps=params.steps,
        crop=params.crop, batch=params.batch, frames_per_sample=params.frames_per_sample, lr=params.lr,
        warmup_steps=params.warmup_steps, seed=params.seed, train_split=params.train_split,
        validation_split=params.validation_split, validation_frames=params.validation_frames,
        threads=params.threads, experiment=params.experiment, track=params.track), storage, settings)
    return {**params.model_dump(), "presets": presets}


def run(context: JobContext) -> dict[str, Any]:
    from model.fit import LADDER_JSON, LADDER_MARKDOWN, fit, format_ladder, plan_fit, write_ladder

    params = FitParams.model_validate(context.params)
    config = fit_config(params, context.storage, context.settings, context.folder / FIT_FOLDER,
                        context.torch_device)
    plan = plan_fit(config)
    recorder = None
    if params.track:
        recorder = start_fit_run(config, config.tracking_uri, f"fit {params.method} {params.target} "
                                                              f"(job {context.job_id[:8]})")
        context.set_mlflow_run(recorder.run_id, recorder.experiment_id)
    try:
        result = fit(config, store=recorder, tracker=recorder,
                     train_tracker=recorder.train_tracker if recorder else None, progress=context.progress,
                     say=context.logger.info, plan=plan)
    except BaseException:
        if recorder is not None:
            recorder.finish("KILLED" if context.cancelled.is_set() else "FAILED")
        raise
    if recorder is not None:
        recorder.finish("FINISHED")
    write_ladder(result, context.folder)
    context.logger.info("ladder:\n%s", format_ladder(result))
    if not result.met:
        run = f", MLflow run {recorder.run_id}" if recorder else ""
        raise JobFailure("target_not_met", f"{result.reason} (ladder: GET /jobs/{context.job_id}/artifacts/"
                         f"{LADDER_MARKDOWN} or {LADDER_JSON}{run})")
    return summary(result, context)


def summary(result, context: JobContext) -> dict[str, Any]:
    from model.fit import LADDER_JSON, LADDER_MARKDOWN

    root = context.storage.root.resolve()
    ladder = []
    for rung in result.to_dict()["ladder"]:
        path = rung.get("checkpoint")
        if path and Path(path).resolve().is_relative_to(root):
            rung["checkpoint"] = str(Path(path).resolve().relative_to(root))
        ladder.append(rung)
    info = result.to_dict()
    return {"family": info["family"], "scale": info["scale"], "target": info["target"],
            "target_description": info["target_description"], "met": info["met"], "chosen": info["chosen"],
            "reason": info["reason"], "registered": info.get("registered"), "alias": info.get("alias"),
            "timing": info.get("timing"), "fit_key": info.get("fit_key"), "ladder": ladder,
            "artifacts": {name: f"/jobs/{context.job_id}/artifacts/{name}" for name in (LADDER_JSON, LADDER_MARKDOWN)}}
