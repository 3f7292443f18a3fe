"""Every path the service and the workers use on disk, under one root (settings.data_dir).

    datasets/<id>/          a model.io.dataset.Dataset (manifest.json + sequence folders)
    jobs/<id>/              job working folder: checkpoints, reports, charts, logs
    results/<id>/           outputs of an infer job: <sequence>/<frame>.exr
    models/<name>/<version>/ checkpoints downloaded from the MLflow registry (cache)
    staging/                uploads being received and validated; moved into place only when complete
    mlflow/                 local MLflow SQLite store and artifacts (when no tracking URI is configured)
    runs/<name>/            checkpoints of `denoiser train` and `denoiser fit` runs given no --out
"""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from core.names import ID_MAX_LENGTH, ID_PATTERN

_ID = re.compile(ID_PATTERN)


def checked_id(value: str, what: str) -> str:
    """An id safe to use as one path component (no separators, no '..'), else ValueError naming it."""
    if not _ID.fullmatch(value) or len(value) > ID_MAX_LENGTH:  # fullmatch: "$" alone passes a final newline
        raise ValueError(f"{what} {value!r} is not a valid id: use letters, digits, '.', '_' and '-' "
                         f"(at most {ID_MAX_LENGTH}, not starting with a punctuation mark)")
    return value


@dataclass(frozen=True)
class Storage:
    root: Path

    @property
    def datasets(self) -> Path:
        return self.root / "datasets"

    @property
    def jobs(self) -> Path:
        return self.root / "jobs"

    @property
    def results(self) -> Path:
        return self.root / "results"

    @property
    def models(self) -> Path:
        return self.root / "models"

    @property
    def staging(self) -> Path:
        return self.root / "staging"

    @property
    def mlflow(self) -> Path:
        return self.root / "mlflow"

    @property
    def runs(self) -> Path:
        return self.root / "runs"

    @property
    def native_kernels(self) -> Path:
        """The compiled native kernels (model/ops/native), unless ``native_cache_dir`` names another folder."""
        return self.root / "native-kernels"

    def ensure(self) -> Storage:
        for folder in (self.datasets, self.jobs, self.results, self.models, self.staging, self.mlflow):
            folder.mkdir(parents=True, exist_ok=True)
        return self

    def dataset(self, dataset_id: str) -> Path:
        return self.datasets / checked_id(dataset_id, "dataset id")

    def job(self, job_id: str) -> Path:
        return self.jobs / checked_id(job_id, "job id")

    def result(self, job_id: str) -> Path:
        return self.results / checked_id(job_id, "job id")

    def model_versions(self, name: str) -> Path:
        """The cached checkpoints of every version of registered model ``name``."""
        return self.models / checked_id(name, "model name")

    def model(self, name: str, version: str | int) -> Path:
        return self.model_versions(name) / checked_id(str(version), "model version")

    def staging_folder(self, token: str) -> Path:
        return self.staging / checked_id(token, "staging token")

    def remove_tree(self, path: Path) -> None:
        """Delete a stored tree by renaming it aside first, so a crash never leaves it half-deleted in place."""
        if not path.exists():
            return
        doomed = self.staging / f"deleting-{path.name}-{id(path):x}"
        path.rename(doomed)
        shutil.rmtree(doomed, ignore_errors=True)


def get_storage() -> Storage:
    from core.settings import get_settings

    return Storage(get_settings().data_dir).ensure()
