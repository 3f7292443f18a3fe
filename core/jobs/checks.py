"""Checks of job parameters against what is stored, shared by the job kinds (domain errors naming the problem)."""

from __future__ import annotations

from model.io.dataset import MANIFEST, Dataset, DatasetError, Sequence
from core.errors import Invalid, NotFound
from core.names import SPLITS
from core.storage import Storage, checked_id


def dataset_root(storage: Storage, dataset_id: str):
    try:
        return storage.dataset(checked_id(dataset_id, "dataset id"))
    except ValueError as error:
        raise Invalid("invalid_id", str(error)) from None


def open_dataset(storage: Storage, dataset_id: str) -> Dataset:
    """The stored dataset, or NotFound naming it (Invalid for a damaged manifest)."""
    root = dataset_root(storage, dataset_id)
    if not (root / MANIFEST).is_file():
        raise NotFound("dataset_not_found", f"dataset {dataset_id!r} does not exist")
    try:
        return Dataset(root)
    except DatasetError as error:
        raise Invalid("invalid_dataset", f"dataset {dataset_id!r} is damaged: {error}") from None


def split_sequences(dataset: Dataset, dataset_id: str, split: str, scale: int | None = None) -> list[Sequence]:
    """The split's sequences (manifests only), checked to be there and, with ``scale``, to hold its references."""
    sequences = dataset.sequences(split)
    if not sequences:
        present = ", ".join(f"{s} ({len(dataset.names(s))})" for s in SPLITS
                            if dataset.names(s)) or "none"
        raise Invalid("empty_split", f"dataset {dataset_id!r} has no sequences in split {split!r} "
                 f"(splits present: {present})")
    if scale is not None:
        missing = [s.name for s in sequences if scale not in s.scales]
        if missing:
            raise Invalid("missing_scale", f"dataset {dataset_id!r}: sequence(s) {', '.join(missing[:5])} of "
                     f"split {split!r} have no references at scale {scale}")
    return sequences


def invalid(error: Exception, code: str = "invalid_params") -> Invalid:
    """A library ValueError / KeyError about the parameters as Invalid with its message."""
    message = error.args[0] if isinstance(error, KeyError) and error.args else str(error)
    return Invalid(code, str(message))
