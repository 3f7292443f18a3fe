"""Tiny stored datasets for the job tests (16x16 synthetic frames written with SequenceWriter, no Mitsuba)."""

from __future__ import annotations

from pathlib import Path

from model.io.dataset import Dataset
from core.storage import Storage
from tests.builders import write_sequence, write_tiny_dataset


def store_dataset(storage: Storage, dataset_id: str = "tiny", test_frames: int = 4) -> Path:
    """Training (alpha, beta), validation (gamma) and test (delta, epsilon: 4 frames, a cut at 2) sequences."""
    root = write_tiny_dataset(storage.dataset(dataset_id))
    dataset = Dataset(root)
    for name, cuts, seed in (("delta", (), 4), ("epsilon", (2,), 5)):
        write_sequence(root, name, test_frames, cuts=cuts, seed=seed)
        dataset.add_sequence_dir(name, "test")
    return root
