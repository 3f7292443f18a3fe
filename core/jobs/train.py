"""The ``train`` job's check and its ``model.training.train`` configuration (shared by the check and the worker)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from model.io.dataset import Dataset
from core.errors import Invalid, NotFound
from core.jobs.checks import invalid, open_dataset, split_sequences
from core.jobs.methods import check_registry_method, checkpoint_method, checkpoint_source
from core.jobs.specs import TrainParams
from core.settings import Settings
from core.storage import Storage


def train_config(params: TrainParams, storage: Storage, settings: Settings, out: Path, device: str,
                 init_from: Path | None = None):
    """``init_from``: the local checkpoint ``params.init_from`` stands for (``initial_weights``)."""
    from model.training.train import TrainConfig
    from model.training.training_settings import TrainingSettings

    training = params.model_dump(include=set(TrainingSettings.model_fields))
    training.update(data=str(storage.dataset(params.dataset)), out=str(out), resume=True, device=device,
                    threads=params.threads or rank_threads(settings, params.world_size // params.nodes),
                    tracking_uri=settings.resolved_tracking_uri(), init_from=str(init_from) if init_from else None)
    return TrainConfig(**training)


def initial_weights(params: TrainParams, storage: Storage) -> Path | None:
    """The checkpoint ``init_from`` names (a registered model, a pretrained model or a stored checkpoint), checked
    to hold the job's method family at its scale; NotFound / Invalid otherwise."""
    if params.init_from is None:
        return None
    path = checkpoint_source(params.init_from, storage)
    if path is None:
        from core.registry import pretrained_dir
        from model.deployment.pretrained import pretrained_names

        raise NotFound("init_from_not_found", f"init_from {params.init_from!r} is no registered model "
                  f"(models:/NAME@ALIAS), pretrained model or checkpoint (a method name has no weights); "
                  f"pretrained models: {', '.join(pretrained_names(pretrained_dir())) or 'none'}")
    source = checkpoint_method(path, f"init_from {params.init_from!r}")
    family = params.method.partition(":")[0]
    if source.get("method") != family or source.get("scale") != params.scale:
        raise Invalid("invalid_init_from", f"init_from {params.init_from!r} holds {source.get('method')}:"
                 f"{source.get('preset')} at scale {source.get('scale')}; it cannot start {params.method} at "
                 f"scale {params.scale}")
    return path


def rank_threads(settings: Settings, world_size: int) -> int | None:
    """Each rank's share of DENOISER_JOB_THREADS (None: unset, each rank takes its share of the cores); a node's
    ranks share its worker's budget."""
    if not settings.job_threads:
        return None
    return max(1, settings.job_threads // max(1, world_size))


def check(params: TrainParams, storage: Storage, settings: Settings) -> dict[str, Any]:
    """Everything ``model.training.train.prepare`` would refuse, found from manifests alone (no frame is decoded)."""
    from model.data.crops import sample_windows

    if params.nodes > settings.max_train_nodes:
        raise Invalid("too_many_nodes", f"nodes {params.nodes} is more than this service allows "
                      f"(DENOISER_MAX_TRAIN_NODES={settings.max_train_nodes})")
    dataset = open_dataset(storage, params.dataset)
    check_registry_method(params.method, params.scale, learned=True)
    init_from = initial_weights(params, storage)
    try:
        train_config(params, storage, settings, storage.jobs / "_check", "cpu", init_from).check()
    except ValueError as error:
        raise invalid(error) from None
    sequences = split_sequences(dataset, params.dataset, params.train_split, params.scale)
    small = [s for s in sequences if s.width < params.crop or s.height < params.crop]
    if small:
        raise Invalid("crop_too_large", f"sequence '{small[0].name}' is {small[0].width}x{small[0].height}, "
                 f"smaller than the {params.crop}x{params.crop} crop; use a smaller crop")
    if not any(sample_windows(s.cuts, len(s), params.frames_per_sample) for s in sequences):
        raise Invalid("sequences_too_short", f"no sequence of split {params.train_split!r} has "
                 f"{params.frames_per_sample} consecutive frames without a camera cut; use fewer "
                 f"frames_per_sample")
    _check_validation_split(dataset, params)
    return params.model_dump()


def _check_validation_split(dataset: Dataset, params: TrainParams) -> None:
    missing = [s.name for s in dataset.sequences(params.validation_split) if params.scale not in s.scales]
    if missing:
        raise Invalid("missing_scale", f"validation sequence(s) {', '.join(missing[:5])} have no references "
                 f"at scale {params.scale}")
