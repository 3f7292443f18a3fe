"""Sequence folders and datasets: manifests, atomic sequence writes, splits and summaries."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from model.io.dataset import Dataset, DatasetError, Sequence, SequenceWriter
from model.io.frames import FrameValidationError

from tests.builders import frame_sequence, make_frame, write_frame_sequence

# Sequences of make_frame frames, with a scene and metadata as a renderer writes them.
write_sequence = functools.partial(write_frame_sequence, scene="cornell", metadata={"spp_reference": 64})


def test_sequence_round_trip(tmp_path):
    written = list(frame_sequence(3, cuts=(0, 2)))
    with SequenceWriter(tmp_path / "seq", "seq", scene="cornell", metadata={"spp_reference": 64}) as writer:
        for frame in written:
            writer.add(frame)
    sequence = Sequence(tmp_path / "seq")
    assert (sequence.name, sequence.scene, sequence.width, sequence.height) == ("seq", "cornell", 6, 4)
    assert sequence.scales == (1, 2) and len(sequence) == 3 and sequence.cuts == [0, 2]
    assert sequence.metadata == {"spp_reference": 64}
    assert sorted(p.name for p in (tmp_path / "seq").iterdir()) == [
        "frame_0000.exr", "frame_0001.exr", "frame_0002.exr", "manifest.json"
    ]
    read = list(sequence)
    assert [f.frame_index for f in read] == [0, 1, 2]
    assert all(f.sequence == "seq" for f in read)  # filled in from the writer's name
    np.testing.assert_array_equal(read[1].color, written[1].color)
    np.testing.assert_array_equal(sequence[-1].reference(2), written[2].reference(2))
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]  # no temporary folder left
    with pytest.raises(IndexError, match="has 3 frames"):
        sequence[3]


def test_exception_mid_sequence_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="renderer crashed"):
        with SequenceWriter(tmp_path / "seq", "seq") as writer:
            for frame in frame_sequence(2):
                writer.add(frame)
            raise RuntimeError("renderer crashed")
    assert list(tmp_path.iterdir()) == []


def test_failed_overwrite_leaves_the_old_sequence_intact(tmp_path):
    write_sequence(tmp_path, "seq", count=2)
    before = {p.name: p.read_bytes() for p in (tmp_path / "seq").iterdir()}
    broken = list(frame_sequence(2, seed=10))
    broken[1].color[0, 0, 0] = np.inf
    with pytest.raises(FrameValidationError, match=r"seq/frame_0001.exr: buffer 'color': 1 pixels are not finite"):
        with SequenceWriter(tmp_path / "seq", "seq", overwrite=True) as writer:
            for frame in broken:
                writer.add(frame)
    assert {p.name: p.read_bytes() for p in (tmp_path / "seq").iterdir()} == before
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]


def test_overwrite_replaces_the_old_sequence(tmp_path):
    write_sequence(tmp_path, "seq", count=3)
    with SequenceWriter(tmp_path / "seq", "seq", overwrite=True) as writer:
        for frame in frame_sequence(2, height=2, width=2, scales=()):
            writer.add(frame)
    sequence = Sequence(tmp_path / "seq")
    assert (len(sequence), sequence.width, sequence.scales) == (2, 2, ())
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]


def test_existing_sequence_is_refused_before_rendering(tmp_path):
    (tmp_path / "seq").mkdir()
    with pytest.raises(FileExistsError, match="overwrite=True"):
        with SequenceWriter(tmp_path / "seq", "seq"):
            pytest.fail("the body must not run")


def test_unserializable_metadata_is_refused_before_rendering(tmp_path):
    with pytest.raises(DatasetError, match="not JSON-serializable"):
        SequenceWriter(tmp_path / "seq", "seq", metadata={"when": object()}).__enter__()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "change, problem",
    [
        (lambda f: setattr(f, "frame_index", 5), r"frame 1: frame_index is 5, expected 1"),
        (lambda f: setattr(f, "references", {1: f.references[1]}), r"reference scales \[1\] differ .* \[1, 2\]"),
        (lambda f: setattr(f, "sequence", "other"), r"frame belongs to sequence 'other'"),
    ],
    ids=["index gap", "scales change", "foreign sequence"],
)
def test_frames_must_continue_the_sequence(tmp_path, change, problem):
    first, second = frame_sequence(2)
    change(second)
    with pytest.raises(DatasetError, match=problem):
        with SequenceWriter(tmp_path / "seq", "seq") as writer:
            writer.add(first)
            writer.add(second)
    assert list(tmp_path.iterdir()) == []


def test_resolution_must_stay_the_same(tmp_path):
    first = make_frame(0, frame_index=0)
    second = make_frame(1, 2, 2, frame_index=1)
    with pytest.raises(DatasetError, match=r"resolution 2x2 differs from the first frame's 6x4"):
        with SequenceWriter(tmp_path / "seq", "tiny") as writer:
            writer.add(first)
            writer.add(second)


def test_empty_sequence_is_an_error(tmp_path):
    with pytest.raises(DatasetError, match="has no frames"):
        with SequenceWriter(tmp_path / "seq", "seq"):
            pass
    assert list(tmp_path.iterdir()) == []


def _edit_manifest(path, edit):
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


@pytest.mark.parametrize(
    "edit, problem",
    [
        (lambda m: m.update(format="denoiser-sequence/9"), r"field 'format' is 'denoiser-sequence/9'"),
        (lambda m: m.pop("width"), r"field 'width' is missing"),
        (lambda m: m.update(height="4"), r"field 'height' is '4', not an integer"),
        (lambda m: m.update(scales=[2, 1]), r"field 'scales' \[2, 1\] is not ascending"),
        (lambda m: m["frames"][1].update(index=2), r"frames\[1\]: field 'index' is 2, expected 1"),
        (lambda m: m["frames"][0].update(file="../x.exr"), r"frames\[0\]: field 'file' is '../x.exr'"),
        (lambda m: m["frames"][0].update(file="gone.exr"), r"frames\[0\]: field 'file': .*gone.exr does not exist"),
        (lambda m: m["frames"][0].update(camera_cut=1), r"field 'camera_cut' is 1, not true or false"),
    ],
)
def test_bad_sequence_manifest_names_file_and_field(tmp_path, edit, problem):
    write_sequence(tmp_path, "seq", count=2)
    _edit_manifest(tmp_path / "seq" / "manifest.json", edit)
    with pytest.raises(DatasetError, match=rf"seq/manifest.json: .*{problem}"):
        Sequence(tmp_path / "seq")


def test_missing_or_broken_manifest_is_named(tmp_path):
    with pytest.raises(DatasetError, match=r"manifest.json: not found"):
        Sequence(tmp_path)
    (tmp_path / "manifest.json").write_text("{oops")
    with pytest.raises(DatasetError, match=r"manifest.json: not valid JSON"):
        Sequence(tmp_path)


def test_frame_disagreeing_with_manifest_is_named(tmp_path):
    sequence = Sequence(write_sequence(tmp_path, "seq", count=2))
    _edit_manifest(sequence.manifest_path, lambda m: m["frames"][1].update(camera_cut=True))
    with pytest.raises(DatasetError, match=r"frame_0001.exr: camera_cut is False but .*manifest.json says True"):
        Sequence(tmp_path / "seq")[1]


def test_dataset_registers_sequences_with_splits(tmp_path):
    dataset = Dataset.create(tmp_path / "data")
    write_sequence(dataset.root, "a", count=3, scene="cornell")
    write_sequence(dataset.root, "b", count=2, scene="kitchen", height=2, width=2, scales=(1,))
    write_sequence(dataset.root, "c", count=1, scene="cornell")
    dataset.add_sequence_dir("a", "train")
    dataset.add_sequence_dir("b", "train")
    dataset.add_sequence_dir("c", "validation")

    reopened = Dataset(tmp_path / "data")
    assert [s.name for s in reopened.sequences()] == ["a", "b", "c"]
    assert [s.name for s in reopened.sequences("train")] == ["a", "b"]
    assert reopened.sequences("test") == []
    assert reopened.summary() == {
        "train": {"sequences": 2, "scenes": ["cornell", "kitchen"], "frames": 5,
                  "resolutions": [[2, 2], [6, 4]], "scales": [1, 2]},
        "validation": {"sequences": 1, "scenes": ["cornell"], "frames": 1, "resolutions": [[6, 4]], "scales": [1, 2]},
        "test": {"sequences": 0, "scenes": [], "frames": 0, "resolutions": [], "scales": []},
    }

    reopened.set_split("c", "test")
    assert Dataset(tmp_path / "data").split_of("c") == "test"
    table = Dataset(tmp_path / "data").format_summary()
    assert table.splitlines()[1:] == [
        "split       sequences  frames  resolutions  scales  scenes",
        "train               2       5  2x2, 6x4     1, 2    cornell, kitchen",
        "validation          0       0  -            -       -",
        "test                1       1  6x4          1, 2    cornell",
    ]
    assert [p.name for p in (tmp_path / "data").iterdir() if p.name.startswith(".")] == []


def test_dataset_errors(tmp_path):
    dataset = Dataset.create(tmp_path)
    write_sequence(tmp_path, "a", count=1)
    with pytest.raises(ValueError, match=r"unknown split 'training'; allowed: train, validation, test"):
        dataset.add_sequence_dir("a", "training")
    dataset.add_sequence_dir("a", "train")
    with pytest.raises(DatasetError, match="already registered"):
        dataset.add_sequence_dir("a", "test")
    with pytest.raises(DatasetError, match="manifest.json: not found"):
        dataset.add_sequence_dir("missing", "test")
    with pytest.raises(DatasetError, match="not a plain folder name"):
        dataset.add_sequence_dir("../a", "test")
    with pytest.raises(DatasetError, match="no sequence named 'zzz'"):
        dataset.set_split("zzz", "test")
    with pytest.raises(ValueError, match="allowed: train, validation, test"):
        dataset.sequences("holdout")
    with pytest.raises(FileExistsError, match="already exists"):
        Dataset.create(tmp_path)
    _edit_manifest(tmp_path / "manifest.json", lambda m: m["sequences"]["a"].update(split="dev"))
    with pytest.raises(DatasetError, match=r"sequences\['a'\]: field 'split' is 'dev'"):
        Dataset(tmp_path)


def test_a_dataset_opened_twice_keeps_what_each_adds(tmp_path):
    # Two processes importing into one dataset each hold a view read before the other's change: every change
    # re-reads the manifest under the dataset's lock, so neither drops the other's sequence.
    first = Dataset.open_or_create(tmp_path / "data")
    second = Dataset.open_or_create(tmp_path / "data")
    for name in ("a", "b", "c"):
        write_sequence(first.root, name, count=1)
    first.add_sequence_dir("a", "train")
    second.add_sequence_dir("b", "train")  # second's view predates "a"
    first.set_split("b", "test")  # first's view predates "b"
    with pytest.raises(DatasetError, match="'a' is already registered"):
        second.add_sequence_dir("a", "validation")  # refused by what is stored, not by a stale view
    second.add_sequence_dir("c", "validation")
    stored = Dataset(tmp_path / "data")
    assert {name: stored.split_of(name) for name in stored.names()} == {"a": "train", "b": "test", "c": "validation"}
    assert second.names() == ["a", "b", "c"] and [p.name for p in stored.root.iterdir() if p.name.startswith(".")] == []


def test_imports_into_one_dataset_from_many_processes_lose_no_sequence(tmp_path):
    from concurrent.futures import ProcessPoolExecutor

    root = tmp_path / "data"
    names = [f"s{index}" for index in range(12)]
    for name in names:
        write_sequence(root, name, count=1)
    with ProcessPoolExecutor(4) as pool:
        list(pool.map(_register, [root] * len(names), names))
    assert Dataset(root).names() == sorted(names)


def _register(root, name):
    Dataset.open_or_create(root).add_sequence_dir(name, "train")
