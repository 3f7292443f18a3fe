"""The ``infer`` job's check and its sequence selection (a split, named sequences, or all)."""

from __future__ import annotations

from typing import Any

from model.io.dataset import Dataset, Sequence
from core.errors import Invalid, NotFound
from core.jobs.checks import open_dataset, split_sequences
from core.jobs.methods import check_registry_method, check_rescalable, checkpoint_method, checkpoint_source
from core.jobs.specs import InferParams
from core.settings import Settings
from core.storage import Storage


def selected_sequences(params: InferParams, storage: Storage) -> list[Sequence]:
    return select_sequences(open_dataset(storage, params.dataset), params, params.dataset)


def select_sequences(dataset: Dataset, params: InferParams, name: str) -> list[Sequence]:
    """The sequences ``params`` select in ``dataset`` (named ``name`` in errors): a split, named ones, or all."""
    if params.split is not None:
        return split_sequences(dataset, name, params.split)
    if params.sequences is not None:
        known = set(dataset.names())
        unknown = [sequence for sequence in params.sequences if sequence not in known]
        if unknown:
            raise NotFound("sequence_not_found", f"dataset {name!r} has no sequence(s) "
                      f"{', '.join(map(repr, unknown))}")
        return [dataset.sequence(sequence) for sequence in dict.fromkeys(params.sequences)]
    sequences = dataset.sequences()
    if not sequences:
        raise Invalid("empty_dataset", f"dataset {name!r} has no sequences")
    return sequences


def check(params: InferParams, storage: Storage, settings: Settings | None = None) -> dict[str, Any]:
    selected_sequences(params, storage)
    path = checkpoint_source(params.model, storage)
    if path is None:
        check_registry_method(params.model, params.scale or 1)
    else:
        config = checkpoint_method(path, params.model)
        if params.scale is not None and config.get("scale") != params.scale:
            check_rescalable(params.model, config, params.scale)
    return params.model_dump()
