"""The ``generate`` job's check: known scenes, and no sequence the job would overwrite (unless asked)."""

from __future__ import annotations

from typing import Any

from model.io.dataset import MANIFEST, Dataset
from core.errors import Conflict, Invalid
from core.jobs.checks import dataset_root
from core.jobs.specs import GenerateParams
from core.settings import Settings
from core.storage import Storage


def check(params: GenerateParams, storage: Storage, settings: Settings | None = None) -> dict[str, Any]:
    from model.data.generate import default_sequence_name
    from model.data.scenes import SCENES

    scenes = sorted(SCENES) if "all" in params.scenes else list(dict.fromkeys(params.scenes))
    unknown = [s for s in scenes if s not in SCENES]
    if unknown:
        raise Invalid("unknown_scene", f"unknown scene {', '.join(map(repr, unknown))}; known scenes: "
                 f"{', '.join(sorted(SCENES))}")
    root = dataset_root(storage, params.dataset)
    if (root / MANIFEST).is_file() and not params.overwrite:
        existing = set(Dataset(root).names())
        taken = [name for name in (default_sequence_name(s, params.seed) for s in scenes) if name in existing]
        if taken:
            raise Conflict("sequence_exists", f"dataset {params.dataset!r} already has sequence(s) "
                      f"{', '.join(taken)}; use another seed or set overwrite")
    return {**params.model_dump(), "scenes": scenes}
