"""FrameBatch.from_bundles: target-resolution buffers at the chosen scale, and none of them for methods."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model.methods.base import FrameBatch
from tests.builders import make_frame

TARGETS = ("reference", "reference_albedo", "reference_specular_albedo")


def test_albedo_references_are_stacked_at_the_chosen_scale():
    bundles = [make_frame(seed=seed, scales=(1, 2), albedo_references=True) for seed in (0, 1)]
    for scale in (1, 2):
        batch = FrameBatch.from_bundles(bundles, scale=scale)
        for name in TARGETS:
            tensor = getattr(batch, name)
            assert tensor.shape == (2, 3, 4 * scale, 6 * scale) and tensor.dtype == torch.float32, name
            assert tensor.is_contiguous(), name
            for index, bundle in enumerate(bundles):
                expected = bundle.target_buffers(scale)[name].transpose(2, 0, 1)
                np.testing.assert_array_equal(tensor[index].numpy(), expected, err_msg=name)


def test_albedo_references_are_none_unless_every_frame_has_them():
    with_them = make_frame(seed=0, albedo_references=True)
    without = make_frame(seed=1)
    mixed = FrameBatch.from_bundles([with_them, without], scale=2)
    assert mixed.reference is not None
    assert mixed.reference_albedo is None and mixed.reference_specular_albedo is None
    assert FrameBatch.from_bundles([with_them], scale=None).reference_albedo is None
    # Only at scales that have a radiance reference; a missing radiance reference stays an error.
    with pytest.raises(KeyError, match="no reference at scale 4"):
        FrameBatch.from_bundles([with_them], scale=4)


def test_without_reference_drops_every_target_buffer():
    batch = FrameBatch.from_bundles([make_frame(albedo_references=True)], scale=2)
    assert set(TARGETS) <= set(batch.tensors())
    stripped = batch.without_reference()
    assert not set(TARGETS) & set(stripped.tensors())
    assert stripped.albedo is batch.albedo and stripped.specular_albedo is batch.specular_albedo
    moved = batch.to("cpu")
    assert moved.reference_specular_albedo is not None
