"""The ``fit`` job's check (family, presets, target, data, checked as a train job of the first preset) and its
``model.fit`` configuration."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from core.errors import Invalid
from core.jobs.checks import invalid, open_dataset, split_sequences
from core.jobs.specs import FitParams, TrainParams
from core.names import RESERVED_ALIAS_PATTERN
from core.settings import Settings
from core.storage import Storage
from model.training.training_settings import FitTrainingSettings


def fit_config(params: FitParams, storage: Storage, settings: Settings, out: Path, device: str):
    from model.fit.plan import FitConfig

    training = params.model_dump(include=set(FitTrainingSettings.model_fields))
    return FitConfig(**training, family=params.method, data=str(storage.dataset(params.dataset)),
                     target=params.target, presets=params.presets, time_at=tuple(params.time_at),
                     timing_frames=params.timing_frames, device=device, out=str(out), alias=params.alias,
                     tracking_uri=settings.resolved_tracking_uri())


def check(params: FitParams, storage: Storage, settings: Settings) -> dict[str, Any]:
    """The family, presets, target and data, checked from manifests (no frame decoded, nothing trained)."""
    from model.fit.plan import default_presets
    from model.fit.target import Target
    from model.methods.registry import method_spec
    from core.jobs import train as train_kind
    from core.jobs.methods import check_registry_method

    if ":" in params.method:
        raise Invalid("invalid_params", f"method takes a family (e.g. wskpn), not a preset: "
                 f"{params.method!r}; choose presets with 'presets'")
    check_registry_method(params.method, params.scale, learned=True)
    presets = list(dict.fromkeys(params.presets)) if params.presets else default_presets(params.method)
    known = method_spec(params.method).presets
    unknown = [p for p in presets if p not in known]
    if unknown:
        raise Invalid("unknown_preset", f"method {params.method!r} has no preset {unknown[0]!r}; presets: "
                 f"{', '.join(known)}")
    try:
        Target.parse(params.target, tuple(params.time_at))
    except ValueError as error:
        raise invalid(error, "invalid_target") from None
    if re.fullmatch(RESERVED_ALIAS_PATTERN, params.alias):  # as MLflow: any case of latest, v or V + digits
        raise Invalid("invalid_params", f"alias {params.alias!r} is reserved by MLflow ('latest', 'vN')")
    dataset = open_dataset(storage, params.dataset)
    split_sequences(dataset, params.dataset, params.validation_split, params.scale)
    # The training settings and data, checked as a train job of the first preset would be.
    training = params.model_dump(include=set(FitTrainingSettings.model_fields))
    train_kind.check(TrainParams(**training, dataset=params.dataset, method=f"{params.method}:{presets[0]}",
                                 track=params.track), storage, settings)
    return {**params.model_dump(), "presets": presets}
