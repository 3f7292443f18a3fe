"""Sequence crops: windows respect cuts, crops line up across scales, flips keep the motion convention, determinism."""

from __future__ import annotations

import itertools
import math
import shutil

import numpy as np
import pytest
import torch

from model.data.crops import (BRIGHTNESS_RANGE, SequenceCrops, collate_crops, longest_run, random_rotation,
                              sample_windows)
from model.io.dataset import Dataset, SequenceWriter
from model.io.frames import box_downsample
from model.ops.warp import backward_warp
from tests.builders import synthetic_frame, write_sequence, write_tiny_dataset


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("crops") / "data")


def test_windows_never_span_a_cut():
    assert sample_windows([], 5, 3) == [0, 1, 2]
    # A cut at 3: windows may start at 3, but none may hold it after their first frame.
    assert sample_windows([3], 6, 3) == [0, 3]
    assert sample_windows([0, 3], 6, 1) == [0, 1, 2, 3, 4, 5]
    assert sample_windows([1, 2], 4, 2) == [2]
    assert sample_windows([], 2, 3) == []


def test_the_longest_run_is_the_longest_run_between_cuts():
    assert longest_run([], 5) == 5
    assert longest_run([3], 6) == 3
    assert longest_run([0, 2], 9) == 7  # a cut at frame 0 starts the first shot: no shorter run
    assert longest_run([1, 2, 8], 10) == 6
    assert longest_run([], 0) == 0


def test_sequences_without_a_window_are_recorded_with_their_longest_run(dataset_root):
    crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=4)
    assert crops.unused == (("alpha", 3),)  # 6 frames cut at 3; beta's 5 frames give windows
    note = crops.unused_note()
    assert note.startswith("1 of 2 sequences of split 'train' hold fewer than 4") and "alpha (3)" in note
    everything = SequenceCrops(dataset_root, "train", crop_size=8, frames=3)
    assert everything.unused == () and everything.unused_note() is None


def test_the_note_names_a_few_short_sequences_and_counts_the_rest(tmp_path):
    dataset = Dataset.create(tmp_path / "data")
    for name, frames in (("a", 2), ("b", 3), ("c", 2), ("long", 5)):
        write_sequence(tmp_path / "data", name, frames=frames, scales=(1,))
        dataset.add_sequence_dir(name, "train")
    crops = SequenceCrops(dataset, "train", crop_size=8, frames=4)
    assert crops.unused == (("a", 2), ("b", 3), ("c", 2))
    assert crops.unused_note(shown=2).startswith("3 of 4 sequences")
    assert "a (2), b (3) and 1 more; fewer frames per sample would use them" in crops.unused_note(shown=2)


def test_samples_come_from_cut_free_windows(dataset_root):
    crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=3)
    # alpha: 6 frames, cut at 3 -> starts 0 and 3; beta: 5 frames -> starts 0, 1, 2.
    assert [(crops.caches[p].name, start) for p, start in crops.windows] == \
        [("alpha", 0), ("alpha", 3), ("beta", 0), ("beta", 1), ("beta", 2)]
    sample = crops.sample(0, epoch=0)
    assert sample["camera_cut"].tolist() == [True, False, False]  # the sample starts without history
    assert sample["color"].shape == (3, 3, 8, 8) and sample["reference"].shape == (3, 3, 8, 8)
    assert sample["depth"].shape == (3, 1, 8, 8) and sample["jitter"].shape == (3, 2)
    # Buffers every training sequence has; the synthetic frames carry no specular albedo.
    assert {"albedo", "normal", "motion", "diffuse", "specular"} <= set(sample) and "specular_albedo" not in sample


def _find_offset(image: torch.Tensor, crop: torch.Tensor) -> tuple[int, int]:
    size = crop.shape[-1]
    matches = [(top, left) for top, left in itertools.product(range(image.shape[-2] - size + 1), repeat=2)
               if torch.equal(image[..., top:top + size, left:left + size], crop)]
    assert len(matches) == 1
    return matches[0]


def test_reference_crop_lines_up_with_the_render_crop_at_every_scale(dataset_root):
    dataset = Dataset(dataset_root)
    scale1 = SequenceCrops(dataset, "train", crop_size=6, frames=2, scale=1, seed=5, augment=False)
    scale2 = SequenceCrops(dataset, "train", crop_size=6, frames=2, scale=2, seed=5, augment=False)
    for index in range(len(scale1)):
        low, high = scale1.sample(index, epoch=1), scale2.sample(index, epoch=1)
        torch.testing.assert_close(low["color"], high["color"], rtol=0, atol=0)  # same crop position
        assert high["reference"].shape == (2, 3, 12, 12)
        # The scale-1 reference is the 2x2 mean of the scale-2 one, so aligned crops agree after pooling.
        torch.testing.assert_close(torch.nn.functional.avg_pool2d(high["reference"], 2), low["reference"])
        # And the crop is a real window of the frame: find its offset, check the reference there.
        position, start = scale1.windows[index]
        frame = scale1.caches[position][start]
        top, left = _find_offset(frame.color[0], low["color"][0])
        torch.testing.assert_close(frame.reference[0, :, top:top + 6, left:left + 6], low["reference"][0])


def _flip(tensor: torch.Tensor, flip_x: bool, flip_y: bool) -> torch.Tensor:
    dims = tuple(d for d, f in ((-1, flip_x), (-2, flip_y)) if f)
    return torch.flip(tensor, dims=dims) if dims else tensor


def test_augmentation_flips_motion_and_jitter_signs_scales_radiance_and_rotates_normals(dataset_root):
    plain_crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=3, augment=False)
    augmented_crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=3, augment=True)
    seen_flips, factors, rotations = set(), [], []
    for index in range(len(plain_crops)):
        for epoch in range(3):
            plain, augmented = plain_crops.sample(index, epoch), augmented_crops.sample(index, epoch)
            # Albedo is neither scaled nor sign-flipped: it tells which flips were drawn.
            flips = [f for f in itertools.product((False, True), repeat=2)
                     if torch.equal(_flip(plain["albedo"], *f), augmented["albedo"])]
            assert len(flips) == 1
            flip_x, flip_y = flips[0]
            seen_flips.add(flips[0])
            factor = float(augmented["color"].sum() / _flip(plain["color"], flip_x, flip_y).sum())
            factors.append(factor)
            for name in ("color", "diffuse", "specular", "reference"):
                torch.testing.assert_close(augmented[name], _flip(plain[name], flip_x, flip_y) * factor)
            # World-space normals move with their pixels and turn by one rotation, the same in every frame.
            before = _flip(plain["normal"], flip_x, flip_y).permute(0, 2, 3, 1).reshape(-1, 3).double()
            after = augmented["normal"].permute(0, 2, 3, 1).reshape(-1, 3).double()
            rotation = torch.linalg.lstsq(before, after).solution.T
            torch.testing.assert_close(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-5, rtol=0)
            assert torch.linalg.det(rotation) == pytest.approx(1.0, abs=1e-5)
            torch.testing.assert_close(after, before @ rotation.T, atol=1e-5, rtol=0)
            rotations.append(rotation)
            signs = torch.tensor([-1.0 if flip_x else 1.0, -1.0 if flip_y else 1.0])
            flipped_motion = _flip(plain["motion"], flip_x, flip_y) * signs.view(2, 1, 1)
            torch.testing.assert_close(augmented["motion"], flipped_motion)
            torch.testing.assert_close(augmented["jitter"], plain["jitter"] * signs)
    assert seen_flips == set(itertools.product((False, True), repeat=2))
    assert BRIGHTNESS_RANGE[0] <= min(factors) and max(factors) <= BRIGHTNESS_RANGE[1]
    assert max(factors) / min(factors) > 1.5  # the factor really varies
    # The rotations vary too, and cover every direction: where the y axis goes, averaged, is near 0.
    assert min(float((r - torch.eye(3, dtype=r.dtype)).abs().max()) for r in rotations) > 0.01
    assert float(torch.stack([r[:, 1] for r in rotations]).mean(0).norm()) < 0.5


def test_flipped_samples_warp_like_the_original(dataset_root):
    """Warping frame 0 to frame 1 with the flipped motion and jitter gives the flipped warp: the signs are right."""
    plain_crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=3, augment=False)
    augmented_crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=3, augment=True)
    checked = 0
    for index, epoch in itertools.product(range(len(plain_crops)), range(3)):
        plain, augmented = plain_crops.sample(index, epoch), augmented_crops.sample(index, epoch)
        flip_x, flip_y = next(f for f in itertools.product((False, True), repeat=2)
                              if torch.equal(_flip(plain["albedo"], *f), augmented["albedo"]))
        if not (flip_x or flip_y):
            continue
        warped, _ = backward_warp(plain["albedo"][:1], plain["motion"][1:], jitter=plain["jitter"][1:])
        warped_flipped, _ = backward_warp(augmented["albedo"][:1], augmented["motion"][1:],
                                          jitter=augmented["jitter"][1:])
        torch.testing.assert_close(warped_flipped, _flip(warped, flip_x, flip_y), atol=1e-5, rtol=1e-5)
        checked += 1
    assert checked >= 3


def test_samples_are_a_function_of_seed_epoch_and_index(dataset_root):
    first = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=11)
    second = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=11)
    other_seed = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=12)
    for index in range(len(first)):
        a, b = first.sample(index, epoch=2), second.sample(index, epoch=2)
        assert all(torch.equal(a[name], b[name]) for name in a)
        assert not torch.equal(a["color"], first.sample(index, epoch=3)["color"])
        assert not torch.equal(a["color"], other_seed.sample(index, epoch=2)["color"])
    second.set_epoch(2)
    assert torch.equal(second[1]["color"], first.sample(1, epoch=2)["color"])


def test_collate_gives_one_batched_frame_per_time_step(dataset_root):
    crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=3)
    frames = collate_crops([crops.sample(i, 0) for i in range(4)])
    assert len(frames) == 3
    for t, frame in enumerate(frames):
        assert frame.batch_size == 4 and frame.color.shape == (4, 3, 8, 8) and frame.jitter.shape == (4, 2)
        assert frame.camera_cut.tolist() == [t == 0] * 4
        assert frame.reference.shape == (4, 3, 8, 8) and frame.diffuse is not None
    torch.testing.assert_close(frames[1].color[2], crops.sample(2, 0)["color"][1])


def test_bad_requests_name_the_problem(dataset_root, tmp_path):
    with pytest.raises(ValueError, match="smaller than the 32x32 crop"):
        SequenceCrops(dataset_root, "train", crop_size=32, frames=2)
    with pytest.raises(ValueError, match="no sequences in split 'test'"):
        SequenceCrops(dataset_root, "test", crop_size=8, frames=2)
    with pytest.raises(ValueError, match="7 consecutive frames"):
        SequenceCrops(dataset_root, "train", crop_size=8, frames=7)
    only_scale_1 = Dataset.create(tmp_path / "data")
    write_sequence(tmp_path / "data", "one", frames=2, scales=(1,))
    only_scale_1.add_sequence_dir("one", "train")
    with pytest.raises(ValueError, match="no reference at scale 2"):
        SequenceCrops(only_scale_1, "train", crop_size=8, frames=2, scale=2)


def test_frames_are_decoded_once(dataset_root, monkeypatch):
    crops = SequenceCrops(dataset_root, "train", crop_size=8, frames=2)
    reads = []
    sequence_type = type(crops.caches[0].sequence)
    original = sequence_type.__getitem__
    monkeypatch.setattr(sequence_type, "__getitem__", lambda self, i: reads.append(i) or original(self, i))
    for epoch in range(3):
        for index in range(len(crops)):
            crops.sample(index, epoch)
    frames_in_windows = 6 + 5 - 2  # every frame once; both first frames were decoded at construction
    assert len(reads) == frames_in_windows
    assert np.isfinite(crops.sample(0, 0)["color"].numpy()).all()


@pytest.fixture(scope="module")
def albedo_dataset_root(tmp_path_factory):
    """One training sequence whose frames carry reference albedos at scales 1 and 2 (box-downsampled)."""
    root = tmp_path_factory.mktemp("albedo_crops") / "data"
    dataset = Dataset.create(root)
    rng = np.random.default_rng(7)
    with SequenceWriter(root / "albedo", "albedo") as writer:
        for index in range(4):
            frame = synthetic_frame(rng, index, 12, 12)
            for attribute in ("reference_albedos", "reference_specular_albedos"):
                finest = rng.uniform(0, 1, (24, 24, 3)).astype(np.float32)
                setattr(frame, attribute, {1: box_downsample(finest, 2), 2: finest})
            writer.add(frame)
    dataset.add_sequence_dir("albedo", "train")
    return root


ALBEDO_TARGETS = ("reference_albedo", "reference_specular_albedo")


def test_reference_albedos_are_cropped_like_the_reference(albedo_dataset_root):
    scale1 = SequenceCrops(albedo_dataset_root, "train", crop_size=5, frames=2, scale=1, seed=2, augment=False)
    scale2 = SequenceCrops(albedo_dataset_root, "train", crop_size=5, frames=2, scale=2, seed=2, augment=False)
    for index in range(len(scale2)):
        low, high = scale1.sample(index, epoch=0), scale2.sample(index, epoch=0)
        position, start = scale2.windows[index]
        frame = scale2.caches[position][start]
        top, left = _find_offset(frame.color[0], high["color"][0])
        for name in ALBEDO_TARGETS:
            assert high[name].shape == (2, 3, 10, 10)
            torch.testing.assert_close(high[name][0], getattr(frame, name)[0, :, 2 * top:2 * top + 10,
                                                                            2 * left:2 * left + 10])
            torch.testing.assert_close(torch.nn.functional.avg_pool2d(high[name], 2), low[name])
    frames = collate_crops([scale2.sample(i, 0) for i in range(2)])
    assert frames[1].reference_albedo.shape == (2, 3, 10, 10)
    assert frames[1].without_reference().reference_specular_albedo is None


def test_reference_albedos_are_flipped_but_not_brightened(albedo_dataset_root):
    plain_crops = SequenceCrops(albedo_dataset_root, "train", crop_size=6, frames=2, scale=2, seed=4, augment=False)
    augmented_crops = SequenceCrops(albedo_dataset_root, "train", crop_size=6, frames=2, scale=2, seed=4)
    seen_flips, factors = set(), []
    for index, epoch in itertools.product(range(len(plain_crops)), range(4)):
        plain, augmented = plain_crops.sample(index, epoch), augmented_crops.sample(index, epoch)
        flip = next(f for f in itertools.product((False, True), repeat=2)
                    if torch.equal(_flip(plain["albedo"], *f), augmented["albedo"]))
        seen_flips.add(flip)
        factor = float(augmented["reference"].sum() / plain["reference"].sum())
        factors.append(factor)
        torch.testing.assert_close(augmented["reference"], _flip(plain["reference"], *flip) * factor)
        for name in ALBEDO_TARGETS:
            torch.testing.assert_close(augmented[name], _flip(plain[name], *flip), rtol=0, atol=0)
    assert len(seen_flips) >= 3 and max(abs(math.log(f)) for f in factors) > 0.2  # flips and brightness happened


def test_reference_albedos_are_left_out_when_a_sequence_lacks_them(albedo_dataset_root, tmp_path):
    root = tmp_path / "mixed"
    shutil.copytree(albedo_dataset_root, root)
    write_sequence(root, "plain", frames=3, size=(12, 12))
    Dataset(root).add_sequence_dir("plain", "train")
    sample = SequenceCrops(root, "train", crop_size=6, frames=2, scale=2).sample(0, 0)
    assert "reference" in sample and not set(ALBEDO_TARGETS) & set(sample)


def test_a_cached_spatial_estimate_is_cropped_flipped_and_brightened_like_the_color(dataset_root):
    from model.methods.oidn import oidn_denoise
    from model.training.spatial_cache import SpatialEstimateCache

    spatial = SpatialEstimateCache("fast")
    plain = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=3, augment=False, spatial=spatial)
    augmented = SequenceCrops(dataset_root, "train", crop_size=8, frames=2, seed=3, augment=True, spatial=spatial)
    full = plain.caches[0][0]
    torch.testing.assert_close(full.spatial_estimate, oidn_denoise(full, "fast"))  # OIDN of the whole frame
    sample, other = plain.sample(0, 0), augmented.sample(0, 0)
    assert sample["spatial_estimate"].shape == sample["color"].shape
    flips = [f for f in itertools.product((False, True), repeat=2)
             if torch.equal(_flip(sample["albedo"], *f), other["albedo"])]
    factor = float(other["color"].sum() / _flip(sample["color"], *flips[0]).sum())
    torch.testing.assert_close(other["spatial_estimate"], _flip(sample["spatial_estimate"], *flips[0]) * factor)


def test_random_rotations_are_proper_and_uniform():
    rng = np.random.default_rng(0)
    rotations = torch.stack([random_rotation(rng) for _ in range(2000)]).double()
    identity = torch.eye(3, dtype=torch.float64).expand(2000, 3, 3)
    torch.testing.assert_close(rotations @ rotations.transpose(1, 2), identity, atol=1e-5, rtol=0)
    assert torch.allclose(torch.linalg.det(rotations), torch.ones(2000, dtype=torch.float64), atol=1e-5)
    # Uniform: every rotation's matrix averages to 0 (a bias towards the identity would show on the diagonal).
    assert float(rotations.mean(0).abs().max()) < 0.05
