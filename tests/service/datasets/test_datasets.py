"""service.datasets (and core.dataset_lock) without HTTP: receiving streams, unpacking archives safely, finding and validating
sequences in the accepted layouts, all-or-nothing commits, frame-by-frame staging."""

from __future__ import annotations

import asyncio
import json
import os
import tarfile
import threading
import zipfile

import pytest

from model.io.dataset import Dataset, Sequence
from model.io.exr import read_frame, write_frame
from service.datasets import archives, catalog, errors, ingest, receive, staged
from core import dataset_lock


def run(coroutine):
    return asyncio.run(coroutine)


async def chunks(*parts: bytes):
    for part in parts:
        yield part


def zip_file(path, members: dict[str, bytes]):
    with zipfile.ZipFile(path, "w") as bundle:
        for name, data in members.items():
            bundle.writestr(name, data)
    return path


# --- save_stream -------------------------------------------------------------------------------------------


def test_save_stream_writes_every_chunk(tmp_path):
    assert run(receive.save_stream(chunks(b"ab", b"cd"), tmp_path / "body", 4, "upload")) == 4
    assert (tmp_path / "body").read_bytes() == b"abcd"


def test_save_stream_past_the_limit_removes_the_partial_file(tmp_path):
    with pytest.raises(errors.UploadTooLarge, match="the upload is at least 5 bytes; the limit is 4 bytes"):
        run(receive.save_stream(chunks(b"ab", b"cde", b"f"), tmp_path / "body", 4, "upload"))
    assert not (tmp_path / "body").exists()


def test_save_stream_trusts_a_large_declared_length_without_reading(tmp_path):
    async def never():
        raise AssertionError("the body must not be read")
        yield b""

    with pytest.raises(errors.UploadTooLarge, match="the frame is 10 bytes"):
        run(receive.save_stream(never(), tmp_path / "body", 4, "frame", declared_length="10"))


# --- unpacking ---------------------------------------------------------------------------------------------


def test_unpack_skips_macos_litter(tmp_path):
    archive = zip_file(tmp_path / "a.zip", {"seq/manifest.json": b"{}", "__MACOSX/seq/._manifest.json": b"x",
                                            "seq/.DS_Store": b"x", "seq/._frame_0000.exr": b"x"})
    assert archives.unpack_archive(archive, tmp_path / "out", 10_000) == "zip"
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").rglob("*")) == [
        "seq", "seq/manifest.json"]


def test_unpack_refuses_duplicates_and_file_folder_clashes(tmp_path):
    with zipfile.ZipFile(tmp_path / "twice.zip", "w") as bundle:
        bundle.writestr("seq/a", b"1")
        with pytest.warns(UserWarning, match="Duplicate name"):
            bundle.writestr("seq/a", b"2")
    with pytest.raises(errors.InvalidUpload, match="'seq/a' appears twice"):
        archives.unpack_archive(tmp_path / "twice.zip", tmp_path / "out1", 10_000)
    archive = zip_file(tmp_path / "clash.zip", {"seq": b"file", "seq/a": b"1"})
    with pytest.raises(errors.InvalidUpload, match="'seq/a' lies inside 'seq', which is a file"):
        archives.unpack_archive(archive, tmp_path / "out2", 10_000)


def test_unpack_refuses_special_files_and_too_many_members(tmp_path, monkeypatch):
    with tarfile.open(tmp_path / "fifo.tar", "w") as bundle:
        fifo = tarfile.TarInfo("seq/pipe")
        fifo.type = tarfile.FIFOTYPE
        bundle.addfile(fifo)
    with pytest.raises(errors.InvalidUpload, match="'seq/pipe' is a device, fifo or other special file"):
        archives.unpack_archive(tmp_path / "fifo.tar", tmp_path / "out1", 10_000)
    monkeypatch.setattr(archives, "MAX_ARCHIVE_MEMBERS", 2)
    archive = zip_file(tmp_path / "many.zip", {f"seq/{i}": b"x" for i in range(3)})
    with pytest.raises(errors.UploadTooLarge, match="more than 2 members"):
        archives.unpack_archive(archive, tmp_path / "out2", 10_000)


def test_archive_of_only_folders_holds_no_files(tmp_path):
    archive = zip_file(tmp_path / "empty.zip", {"seq/": b""})
    with pytest.raises(errors.InvalidUpload, match="holds no files"):
        archives.unpack_archive(archive, tmp_path / "out", 10_000)


# --- layouts -----------------------------------------------------------------------------------------------


def test_one_sequence_folder_contents_at_the_top(tmp_path, tiny_sequence):
    tiny_sequence(tmp_path / "cam_7", 2)
    found = ingest.find_sequences(tmp_path / "cam_7", "test")
    assert [(s.name, s.path, s.split, s.scene) for s in found] == [("cam_7", tmp_path / "cam_7", "test", "cornell")]


def test_one_wrapped_sequence_folder(tmp_path, tiny_sequence):
    tiny_sequence(tmp_path / "up" / "export" / "cam_7", 2)
    found = ingest.find_sequences(tmp_path / "up", "train")
    assert [(s.name, s.path) for s in found] == [("cam_7", tmp_path / "up" / "export" / "cam_7")]


def test_folder_must_be_named_after_its_sequence(tmp_path, tiny_sequence):
    tiny_sequence(tmp_path / "up" / "cam_7", 1)
    (tmp_path / "up" / "cam_7").rename(tmp_path / "up" / "renamed")
    tiny_sequence(tmp_path / "up" / "cam_8", 1)
    with pytest.raises(errors.InvalidUpload, match="sequence folder renamed holds sequence 'cam_7'"):
        ingest.find_sequences(tmp_path / "up", "train")


def test_unlisted_files_and_folders_are_refused(tmp_path, tiny_sequence):
    tiny_sequence(tmp_path / "up" / "cam_7", 1)
    (tmp_path / "up" / "cam_7" / "frame_0009.exr").write_bytes(b"x")
    with pytest.raises(errors.InvalidUpload, match="cam_7/frame_0009.exr is not a frame listed in cam_7/manifest"):
        ingest.find_sequences(tmp_path / "up", "train")

    tiny_sequence(tmp_path / "data" / "listed", 1)
    tiny_sequence(tmp_path / "data" / "stray", 1)
    (tmp_path / "data" / "manifest.json").write_text(json.dumps(
        {"format": "denoiser-dataset/1", "sequences": {"listed": {"split": "train", "scene": None}}}))
    with pytest.raises(errors.InvalidUpload, match="stray is not listed in manifest.json"):
        ingest.find_sequences(tmp_path / "data", "train")


def test_unreadable_top_manifest_is_refused(tmp_path):
    (tmp_path / "up").mkdir()
    (tmp_path / "up" / "manifest.json").write_text("{not json")
    with pytest.raises(errors.InvalidUpload, match="manifest.json: not valid JSON"):
        ingest.find_sequences(tmp_path / "up", "train")


def test_a_manifest_of_another_format_is_left_out(tmp_path, tiny_sequence):
    tiny_sequence(tmp_path / "up" / "cam_7", 1)
    (tmp_path / "up" / "manifest.json").write_text('{"format": "other/1"}')
    ignored = []
    assert [s.name for s in ingest.find_sequences(tmp_path / "up", "train", ignored)] == ["cam_7"]
    assert ignored == ["manifest.json"]
    (tmp_path / "alone").mkdir()
    (tmp_path / "alone" / "manifest.json").write_text('{"format": "other/1"}')
    with pytest.raises(errors.InvalidUpload, match="holds no sequence folder"):
        ingest.find_sequences(tmp_path / "alone", "train")


def test_frames_of_one_sequence_must_have_the_same_buffers(tmp_path, tiny_frames):
    from model.io.dataset import SequenceWriter

    frames = tiny_frames(2)
    frames[1].diffuse = frames[1].specular = None
    with SequenceWriter(tmp_path / "up" / "cam", "cam") as writer:
        for frame in frames:
            writer.add(frame)
    with pytest.raises(errors.InvalidUpload, match="cam/frame_0001.exr: buffers .* differ from the first frame's"):
        ingest.find_sequences(tmp_path / "up", "train")


# --- commits -----------------------------------------------------------------------------------------------


def test_failed_move_rolls_every_sequence_back(storage, tmp_path, tiny_sequence, monkeypatch):
    tiny_sequence(tmp_path / "first" / "seq_a", 1)
    with dataset_lock.workspace(storage, "test") as work:
        ingest._create_dataset(storage, "data", ingest.find_sequences(tmp_path / "first", "train"), work)
    before = {p.relative_to(storage.datasets): p.read_bytes() for p in storage.datasets.rglob("*") if p.is_file()}
    tiny_sequence(tmp_path / "more" / "seq_a", 2, seed=3)  # replaces the stored one
    tiny_sequence(tmp_path / "more" / "seq_b", 1)
    staged = ingest.find_sequences(tmp_path / "more", "train")
    real_rename = os.rename

    def rename(source, target):
        if str(source).endswith("more/seq_b"):
            raise OSError(28, "No space left on device")
        real_rename(source, target)

    monkeypatch.setattr(os, "rename", rename)
    with dataset_lock.workspace(storage, "test") as work, pytest.raises(OSError, match="No space left"):
        ingest._add_to_dataset(storage, "data", staged, work, replace=True)
    monkeypatch.setattr(os, "rename", real_rename)
    after = {p.relative_to(storage.datasets): p.read_bytes() for p in storage.datasets.rglob("*") if p.is_file()}
    assert after == before
    assert len(Sequence(tmp_path / "more" / "seq_a")) == 2  # the staged folder is back where it was


def test_ingest_into_a_missing_dataset_or_a_taken_id(storage, tmp_path, tiny_sequence, make_archive):
    tiny_sequence(tmp_path / "up" / "seq_a", 1)
    body = make_archive(tmp_path / "up")
    for create, error in ((False, errors.UnknownDataset), (True, None), (True, errors.UploadConflict)):
        with dataset_lock.workspace(storage, "upload") as work:
            (work / "upload.bin").write_bytes(body)
            call = lambda: ingest.ingest_archive(storage, work / "upload.bin", work, "data", create=create,  # noqa
                                                 max_unpacked_bytes=10**6)
            if error is None:
                assert call().sequences[0].name == "seq_a"
            else:
                with pytest.raises(error):
                    call()
    assert Dataset(storage.datasets / "data").names() == ["seq_a"]


def test_list_skips_damaged_folders_and_delete_of_unknown_raises(storage, tmp_path, tiny_sequence):
    (storage.datasets / "broken").mkdir()
    (storage.datasets / "broken" / "manifest.json").write_text("[]")
    assert catalog.list_datasets(storage) == []
    with pytest.raises(errors.UnknownDataset, match="'nope' does not exist"):
        catalog.delete_dataset(storage, "nope")


# --- frame-by-frame ----------------------------------------------------------------------------------------


def test_staged_frames_carry_the_sequence_name(storage, tmp_path, tiny_frames):
    unnamed, named = tiny_frames(2, sequence="")[0], tiny_frames(2, sequence="cam")[1]
    write_frame(tmp_path / "0.exr", unnamed)
    write_frame(tmp_path / "1.exr", named)
    sent = (tmp_path / "1.exr").read_bytes()
    staged.stage_frame(storage, "live", "cam", tmp_path / "0.exr")
    state = staged.stage_frame(storage, "live", "cam", tmp_path / "1.exr")
    assert (state.frames, state.split, state.scene) == (2, "train", None)
    folder = storage.staging / "sequences" / "live" / "cam"
    assert read_frame(folder / "frame_0000.exr").sequence == "cam"  # rewritten with the name filled in
    assert (folder / "frame_0001.exr").read_bytes() == sent  # already named: moved as sent
    detail = staged.commit_staged_sequence(storage, "live", "cam")
    assert [(s.name, s.frames) for s in detail.sequences] == [("cam", 2)]
    assert not folder.exists() and not folder.with_name("cam.json").exists()


def test_concurrent_uploads_of_the_same_frame_index_store_one(storage, tmp_path, tiny_frames):
    frame = tiny_frames(1)[0]
    outcomes = []

    def upload(number):
        path = write_frame(tmp_path / f"{number}.exr", frame)
        try:
            outcomes.append(staged.stage_frame(storage, "live", "cam", path).frames)
        except errors.UploadConflict as error:
            outcomes.append(error.code)

    threads = [threading.Thread(target=upload, args=(n,)) for n in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(outcomes, key=str) == [1] + ["frame_out_of_order"] * 3
    assert staged.staged_sequence(storage, "live", "cam").frames == 1


def test_workspace_is_removed_even_after_an_error(storage):
    with pytest.raises(RuntimeError), dataset_lock.workspace(storage, "upload") as work:
        (work / "file").write_bytes(b"x")
        raise RuntimeError("boom")
    assert list(storage.staging.iterdir()) == []


def test_ids_are_checked():
    assert catalog.new_dataset_id("kitchens") == "kitchens"
    assert catalog.new_dataset_id(None).startswith("dataset-")
    with pytest.raises(errors.InvalidUpload, match="dataset id 'a/b' is not a valid id"):
        catalog.new_dataset_id("a/b")
