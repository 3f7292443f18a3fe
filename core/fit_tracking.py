"""The MLflow side of every fit, the CLI's and the job's: ``MLflowFit`` implements ``model.fit.choice.LadderTracker``
(one parent run per fit: per-preset params and metrics, ``ladder.json`` and ``ladder.md`` as artifacts) and
``model.fit.runner.ModelStore`` (model versions: found by tags or by run, downloaded, registered from the parent run,
tagged, aliased); ``train_tracker(preset)`` gives each preset's training its own run, a child of the parent
(tag ``mlflow.parentRunId``)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path
from typing import Any


class MLflowFit:
    """The fit's parent run and the registry calls of ``model.fit`` (see the module notes)."""

    def __init__(self, tracking_uri: str | None, experiment: str, run_name: str) -> None:
        from core.tracking import MLflowTracker

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

        from core.tracking import PARAM_VALUE_LIMIT

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
        from core.tracking import MLflowTracker

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
        from core.tracking import CHECKPOINT_ARTIFACT, download_registered_checkpoint

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
    recorder.start({"kind": "fit", "method": config.family, "steps": config.steps, "epochs": config.epochs,
                    "crop": config.crop, "batch": config.batch, "frames_per_sample": config.frames_per_sample,
                    "lr": config.lr, "seed": config.seed, "validation_split": config.validation_split,
                    "validation_frames": config.validation_frames})
    return recorder
