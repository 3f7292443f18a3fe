"""Stored datasets: ids and names, inspection, listing and deletion."""

from __future__ import annotations

import logging
import uuid

import OpenEXR

from model.io.dataset import Dataset, DatasetError, MANIFEST, SPLITS, Sequence
from model.io.exr import CHANNEL_SLOTS
from model.io.frames import BUFFERS
from service.datasets.errors import InvalidUpload, UnknownDataset
from service.datasets.descriptions import DatasetDetail, DatasetSummary, SequenceInfo, SplitSummary
from core.dataset_lock import dataset_lock
from core.storage import Storage, checked_id

log = logging.getLogger("denoiser.datasets")


def checked_dataset_id(dataset_id: str) -> str:
    return _checked_name(dataset_id, "dataset id")


def checked_sequence_name(name: str) -> str:
    return _checked_name(name, "sequence name")


def _checked_name(value: str, what: str) -> str:
    try:
        return checked_id(value, what)
    except ValueError as error:
        raise InvalidUpload("invalid_name", str(error)) from None


def new_dataset_id(name: str | None) -> str:
    """The given name (a valid id) or, without one, "dataset-" plus a short random suffix."""
    if name is not None:
        return checked_dataset_id(name)
    return f"dataset-{uuid.uuid4().hex[:8]}"


def dataset_exists(storage: Storage, dataset_id: str) -> bool:
    return (storage.dataset(checked_dataset_id(dataset_id)) / MANIFEST).is_file()


def _open(storage: Storage, dataset_id: str) -> Dataset:
    root = storage.dataset(checked_dataset_id(dataset_id))
    if not (root / MANIFEST).is_file():
        raise UnknownDataset("not_found", f"dataset {dataset_id!r} does not exist")
    return Dataset(root)


def sequence_buffers(sequence: Sequence) -> list[str]:
    """Buffers of the sequence's first frame, from the EXR headers only (no pixels decoded)."""
    present: set[str] = set()
    for part in OpenEXR.File(str(sequence.frame_path(0)), header_only=True).parts:
        for channel in part.header["channels"]:
            slot = CHANNEL_SLOTS.get(channel.name)
            if slot is not None:
                present.add(slot[0])
    return [name for name in BUFFERS if name in present]


def describe_dataset(storage: Storage, dataset_id: str) -> DatasetDetail:
    dataset = _open(storage, dataset_id)
    sequences = []
    for sequence in dataset.sequences():
        sequences.append(SequenceInfo(
            name=sequence.path.name, split=dataset.split_of(sequence.path.name), scene=sequence.scene,
            frames=len(sequence), width=sequence.width, height=sequence.height, scales=list(sequence.scales),
            buffers=sequence_buffers(sequence), camera_cuts=sequence.cuts,
        ))
    splits = {split: SplitSummary(**summary) for split, summary in dataset.summary().items()}
    return DatasetDetail(
        id=dataset_id,
        frames=sum(s.frames for s in sequences),
        scenes=sorted({s.scene for s in sequences if s.scene is not None}),
        splits=splits,
        sequences=sequences,
    )


def list_datasets(storage: Storage) -> list[DatasetSummary]:
    """Every stored dataset, by id; reads manifests only."""
    if not storage.datasets.is_dir():
        return []
    summaries = []
    for root in sorted(storage.datasets.iterdir()):
        try:
            dataset = Dataset(root)
            sequences = dataset.sequences()
        except (DatasetError, OSError) as error:  # deleted meanwhile, or damaged on disk: list the others
            log.warning("skipping dataset folder %s: %s", root, error)
            continue
        summaries.append(DatasetSummary(
            id=root.name,
            sequences=len(sequences),
            frames=sum(len(s) for s in sequences),
            scenes=sorted({s.scene for s in sequences if s.scene is not None}),
            splits={split: len(dataset.names(split)) for split in SPLITS},
        ))
    return summaries


def delete_dataset(storage: Storage, dataset_id: str) -> None:
    _open(storage, dataset_id)  # 404 before a lock file is made for an unknown id
    with dataset_lock(storage, checked_dataset_id(dataset_id)):
        _open(storage, dataset_id)
        storage.remove_tree(storage.dataset(dataset_id))
