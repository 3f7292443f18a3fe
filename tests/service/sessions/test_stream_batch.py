"""service.sessions.stream_batch: a stream message's batch equals the reference reading's (read_bundle_buffers, then
FrameBatch.from_bundles) bit for bit, with the same repairs and the same refusals, and clean frames take the fast
way."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import service.sessions.stream_batch as stream_batch
from model.io.frames import FrameError, NORMAL_LENGTH_TOLERANCE
from model.methods.base import FrameBatch
from service.sessions.stream_batch import stream_frame_batch
from client.codec import decode_frame, encode_bundle
from tests.builders import synthetic_frame

FIELDS = [field.name for field in dataclasses.fields(FrameBatch)]


def frame(seed: int = 0, size: int = 12, **changes):
    rng = np.random.default_rng(seed)
    base = synthetic_frame(rng, 3, size, size + 2, scales=(1,))
    extra = {"specular_albedo": rng.uniform(0, 1, size=base.color.shape).astype(np.float32),
             "roughness": rng.uniform(0, 1, size=base.depth.shape).astype(np.float32)}
    return dataclasses.replace(base, **{**extra, **changes})


REFERENCE = stream_batch._reference_batch


def reference(message) -> tuple[FrameBatch, tuple[str, ...]]:
    return REFERENCE(message, "cpu", "frame message")


def assert_same(got: tuple[FrameBatch, tuple[str, ...]], want: tuple[FrameBatch, tuple[str, ...]]) -> None:
    assert got[1] == want[1]
    for name in FIELDS:
        a, b = getattr(got[0], name), getattr(want[0], name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.dtype == b.dtype and a.shape == b.shape, name
            assert torch.equal(a, b) or (a.isnan() == b.isnan()).all() and torch.equal(a.nan_to_num(), b.nan_to_num())


@pytest.fixture
def fast_way_taken(monkeypatch):
    """Counts the frames that went the reference way (the test then says how many should have)."""
    calls = []

    def counted(message, device, source):
        calls.append(message.frame_index)
        return reference(message)

    monkeypatch.setattr(stream_batch, "_reference_batch", counted)
    return calls


@pytest.mark.parametrize("dtype", ["float32", "float16"])
@pytest.mark.parametrize("buffers", [None, ("color", "albedo", "normal", "depth", "motion"),
                                     ("color", "albedo", "normal", "depth", "motion", "roughness")])
def test_a_clean_frame_takes_the_fast_way_and_equals_the_reference(dtype, buffers, fast_way_taken):
    bundle = frame()
    depth = bundle.depth.copy()
    depth[0, :5] = 0.0  # nothing hit: the normal there is dropped, whatever it was
    normal = bundle.normal.copy()
    normal[0, :5] = [3.0, -2.0, 0.5]
    message = decode_frame(encode_bundle(dataclasses.replace(bundle, depth=depth, normal=normal), dtype=dtype,
                                         buffers=buffers))
    got = stream_frame_batch(message)
    assert fast_way_taken == []
    assert_same(got, reference(message))
    assert got[0].normal[0, :, 0, :5].eq(0).all()


def test_the_batch_owns_its_memory(fast_way_taken):
    message = decode_frame(encode_bundle(frame(), dtype="float32"))
    before = message.buffers["color"].copy()
    batch = stream_frame_batch(message).batch
    batch.color.mul_(2)  # a view of the (read-only) message would refuse this or change the message
    np.testing.assert_array_equal(message.buffers["color"], before)
    assert fast_way_taken == []


@pytest.mark.parametrize("infinite_normal", [False, True])
def test_non_finite_and_out_of_range_values_pass_to_the_sanitizer_unchanged(infinite_normal, fast_way_taken):
    bundle = frame(seed=2)
    color, normal, depth = bundle.color.copy(), bundle.normal.copy(), bundle.depth.copy()
    color[1, 1] = np.nan
    color[2, 2, 0] = -4.0
    normal[4, 4] = [np.nan, 1.0, 0.0]
    depth[5, 5] = np.nan
    if infinite_normal:  # its length is no test of the tolerance: the reference way, to be sure
        normal[3, 3] = [np.inf, 0.0, 0.0]
    broken = dataclasses.replace(bundle, color=color, normal=normal, depth=depth, diffuse=None, specular=None)
    message = decode_frame(encode_bundle(broken))
    assert_same(stream_frame_batch(message), reference(message))
    assert fast_way_taken == ([3] if infinite_normal else [])


@pytest.mark.parametrize("factor, repaired", [(1.05, True), (1 + NORMAL_LENGTH_TOLERANCE * 0.9999, False)])
def test_normals_off_unit_length_or_near_the_bound_go_the_reference_way(factor, repaired, fast_way_taken):
    bundle = frame(seed=1)
    normal = bundle.normal.copy()
    normal[2:4] *= factor
    message = decode_frame(encode_bundle(dataclasses.replace(bundle, normal=normal)))
    got = stream_frame_batch(message)
    assert fast_way_taken == [3]
    assert_same(got, reference(message))
    assert bool(got[1]) == repaired
    if repaired:
        assert "normal: 24 pixels renormalised" in got[1][0]


def test_frames_the_reference_refuses_are_refused_with_its_message():
    bundle = frame(seed=4)
    wrong_normals = decode_frame(encode_bundle(dataclasses.replace(bundle, normal=bundle.normal * 2)))
    bad_split = decode_frame(encode_bundle(dataclasses.replace(bundle, diffuse=bundle.diffuse * 3)))
    half_split = decode_frame(encode_bundle(dataclasses.replace(bundle, specular=None)))
    for message, buffer in ((wrong_normals, "normal"), (bad_split, "diffuse"), (half_split, "specular")):
        with pytest.raises(FrameError) as fast:
            stream_frame_batch(message, source="frame message")
        with pytest.raises(FrameError) as slow:
            reference(message)
        assert str(fast.value) == str(slow.value) and fast.value.buffer == buffer


def _broken(bundle, seed: int):
    """One value of the frame made something the input check repairs (chosen by ``seed``), or nothing."""
    rng = np.random.default_rng(seed)
    changes = {}
    choice = seed % 8
    y, x = rng.integers(0, bundle.height), rng.integers(0, bundle.width)
    for name, value in (("color", np.nan), ("albedo", 1.5), ("depth", -1.0), ("motion", np.inf),
                        ("roughness", -0.2), ("specular_albedo", np.nan)):
        if choice == 0:
            array = getattr(bundle, name).copy()
            array[y, x] = value
            changes[name] = array
            break
        choice -= 1
    frame_changes = {"jitter": (0.75, 0.0)} if choice == 0 else {}
    return dataclasses.replace(bundle, **changes, **frame_changes)


@pytest.mark.parametrize("seed", range(16))
def test_the_plainly_valid_verdict_is_the_input_checks(seed, fast_way_taken):
    """A frame the read calls plainly valid is one the input check returns untouched and reports clean; a clean
    frame is called so (the step then skips the check), a frame with anything to repair is not."""
    from model.io.sanitize import sanitize_frame

    bundle = _broken(frame(seed=seed), seed)
    read = stream_frame_batch(decode_frame(encode_bundle(bundle, dtype="float16" if seed % 2 else "float32")))
    checked, report = sanitize_frame(read.batch)
    assert read.plainly_valid == (checked is read.batch and report.clean)
    assert read.plainly_valid == (seed % 8 == 7)  # seeds 7 and 15 break nothing
