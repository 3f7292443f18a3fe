"""OIDN's per-frame output is computed once per stored frame, kept on disk, and keyed by what OIDN reads."""

from __future__ import annotations

import numpy as np
import torch

from model.methods.oidn import oidn_denoise
from model.methods.registry import example_batch
from model.training.spatial_cache import SpatialEstimateCache


def test_computed_once_then_read_from_memory_and_disk(tmp_path):
    frame = example_batch(16, 16, seed=1)
    cache = SpatialEstimateCache("fast", tmp_path)
    first = cache.estimate(frame)
    torch.testing.assert_close(first, oidn_denoise(frame, "fast"))
    assert cache.estimate(frame) is first and cache.computed == 1
    assert len(list((tmp_path / ".cache" / "spatial").glob("*.npy"))) == 1

    fresh = SpatialEstimateCache("fast", tmp_path)  # another process: the file is reused
    torch.testing.assert_close(fresh.estimate(frame), first)
    assert fresh.computed == 0


def test_another_frame_or_quality_is_not_served_a_stale_result(tmp_path):
    frame = example_batch(16, 16, seed=1)
    fast = SpatialEstimateCache("fast", tmp_path)
    fast.estimate(frame)
    changed = example_batch(16, 16, seed=1)
    changed.normal = -changed.normal
    assert fast.key(changed) != fast.key(frame)
    assert SpatialEstimateCache("high", tmp_path).key(frame) != fast.key(frame)


def test_a_torn_file_is_recomputed_and_an_unwritable_folder_keeps_results_in_memory(tmp_path):
    frame = example_batch(16, 16, seed=2)
    cache = SpatialEstimateCache("fast", tmp_path)
    path = tmp_path / ".cache" / "spatial" / f"{cache.key(frame)}.npy"
    path.parent.mkdir(parents=True)
    path.write_bytes(b"not an array")
    torch.testing.assert_close(cache.estimate(frame), oidn_denoise(frame, "fast"))
    assert cache.computed == 1

    blocker = tmp_path / "file"
    blocker.write_text("a file where the dataset folder should be")
    memory_only = SpatialEstimateCache("fast", blocker)
    memory_only.estimate(frame)
    assert memory_only.folder is None and memory_only.estimate(frame) is not None


def test_two_writers_of_the_same_frame_do_not_trip_over_each_other(tmp_path, monkeypatch):
    # Another process (here: a second cache, nested inside the first one's write) stores the same frame meanwhile.
    frame = example_batch(16, 16, seed=3)
    first, second = SpatialEstimateCache("fast", tmp_path), SpatialEstimateCache("fast", tmp_path)
    save = np.save
    interleaved = []

    def save_while_another_writes(file, array):
        save(file, array)
        if not interleaved:
            interleaved.append(None)  # the second writer's own save goes straight through
            interleaved[0] = second.estimate(frame)

    monkeypatch.setattr(np, "save", save_while_another_writes)
    result = first.estimate(frame)
    assert interleaved[0] is not None and first.folder is not None and second.folder is not None  # neither gave up on the disk
    assert [path.name for path in tmp_path.rglob("*.npy")] == [f"{first.key(frame)}.npy"]
    assert torch.equal(result, interleaved[0])
