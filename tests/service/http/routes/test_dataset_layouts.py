"""Uploads in other layouts: a Blender Cycles folder converted on upload, extra channels dropped from stored
frames, frames without a frame index appended in order."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from fastapi.testclient import TestClient

from model.io.dataset import Dataset
from model.io.exr import read_frame
from service.http.routes import datasets
from tests.model.layouts.exr_builders import (
    BLENDER_ORBIT,
    blender_like_bomb,
    bundle_channels,
    upscaled_copy,
    write_channels,
)


@pytest.fixture
def api(make_app) -> TestClient:
    return TestClient(make_app(datasets.router))


def upload(api, body: bytes, path: str = "/datasets", **params):
    return api.post(path, content=body, headers={"Content-Type": "application/zip"}, params=params)


def test_a_blender_cycles_render_folder_uploads_with_its_layout(api, storage, tmp_path, make_archive):
    folder = tmp_path / "orbit"
    shutil.copytree(BLENDER_ORBIT, folder)
    response = upload(api, make_archive(tmp_path, prefix=""), name="blender", layout="blender-cycles", split="test")
    assert response.status_code == 201, response.text
    detail = response.json()
    assert [(s["name"], s["split"], s["frames"], s["scales"]) for s in detail["sequences"]] == [
        ("orbit", "test", 4, [1])]
    stored = Dataset(storage.datasets / "blender").sequence("orbit")
    assert stored[3].reference(1).shape == (32, 32, 3)
    assert "X-Import-Warnings" not in response.headers
    # Without the layout, the same archive is not our format: refused, naming the file and the layouts to choose.
    refused = upload(api, make_archive(tmp_path), name="plain")
    assert refused.status_code == 400
    assert refused.json()["error"]["message"].startswith("orbit/frame_0000.exr: buffer 'color': required buffer is "
                                                         "missing: layout 'denoiser'")
    assert "blender-cycles" in refused.json()["error"]["message"]


def test_a_renderers_own_manifest_in_its_folder_is_left_out_and_named(api, storage, tmp_path, make_archive):
    folder = tmp_path / "orbit"
    shutil.copytree(BLENDER_ORBIT, folder)
    (folder / "manifest.json").write_text('{"format": "cycles-export/2", "frames": 4}')
    response = upload(api, make_archive(tmp_path, prefix=""), name="own", layout="blender-cycles")
    assert response.status_code == 201, response.text
    assert response.headers["X-Ignored-Files"] == "orbit/cameras.json, orbit/manifest.json"
    assert len(Dataset(storage.datasets / "own").sequence("orbit")) == 4
    # This project's manifest is still read as one: a frame bundle upload sent with a renderer's layout is refused.
    (folder / "manifest.json").write_text('{"format": "denoiser-sequence/1"}')
    refused = upload(api, make_archive(tmp_path, prefix=""), name="ours", layout="blender-cycles")
    assert refused.status_code == 400 and "upload it without layout=" in refused.json()["error"]["message"]


def test_unknown_layouts_are_refused_before_reading_the_body(api):
    response = upload(api, b"PK\x05\x06" + bytes(18), layout="arnold")
    assert response.status_code == 400
    error = response.json()["error"]
    assert error["code"] == "invalid_layout" and "built-in layouts are denoiser, blender-cycles, generic" in \
        error["message"]


def test_extra_channels_are_dropped_from_stored_frames_and_reported(api, storage, tmp_path, tiny_sequence,
                                                                    make_archive):
    folder = tiny_sequence(tmp_path / "up" / "seq_a", 2)
    frame = read_frame(folder / "frame_0001.exr")
    channels = bundle_channels(frame)
    channels.update({f"reference.{c}": frame.reference(1)[..., i] for i, c in enumerate("RGB")})
    channels["object_id"] = np.full(frame.depth.shape, 3, np.uint32)
    write_channels(folder / "frame_0001.exr", channels,
                   {"jitter": np.array(frame.jitter), "frame_index": 1, "sequence": "seq_a"})
    response = upload(api, make_archive(tmp_path / "up"), name="tiny")
    assert response.status_code == 201, response.text
    assert response.headers["X-Ignored-Channels"] == "object_id"
    stored = read_frame(storage.datasets / "tiny" / "seq_a" / "frame_0001.exr")  # strict: no unknown channels
    np.testing.assert_array_equal(stored.color, frame.color)


def test_frames_without_a_frame_index_are_appended_in_order(api, tmp_path, tiny_frames):
    for index, frame in enumerate(tiny_frames(2)):
        channels = bundle_channels(frame)
        channels["position.X"] = frame.depth
        path = write_channels(tmp_path / f"{index}.exr", channels, {"jitter": np.array(frame.jitter)})
        response = api.post("/datasets/live/sequences/cam/frames", content=path.read_bytes(),
                            headers={"Content-Type": "image/x-exr"})
        assert response.status_code == 200, response.text
        assert response.json()["frames"] == index + 1
        assert response.headers["X-Ignored-Channels"] == "position.X"
    # Blender numbers its frames from its timeline's start: in its layout, frames are appended in order too.
    for path in sorted(BLENDER_ORBIT.glob("frame_*.exr"))[:2]:
        response = api.post("/datasets/live/sequences/blender/frames", content=path.read_bytes(),
                            headers={"Content-Type": "image/x-exr"}, params={"layout": "blender-cycles"})
        assert response.status_code == 200, response.text
    assert response.json()["frames"] == 2
    assert api.post("/datasets/live/sequences/blender/commit").status_code == 201


def test_frames_declaring_too_many_pixels_are_413_before_decoding_in_any_layout(make_app, storage, tmp_path,
                                                                                  make_archive, monkeypatch):
    import model.io.exr

    api = TestClient(make_app(datasets.router, max_frame_pixels=1024))
    # Within the limit: the fixture's 32x32 frames (6 pass parts each) and their references rendered at 2x.
    folder = tmp_path / "up" / "orbit"
    shutil.copytree(BLENDER_ORBIT, folder)
    for path in sorted((folder / "references").glob("*.exr")):
        upscaled_copy(path, path, 2)
    response = upload(api, make_archive(tmp_path / "up", prefix=""), name="ok", layout="blender-cycles")
    assert response.status_code == 201, response.text
    assert response.json()["sequences"][0]["scales"] == [1, 2]

    decoded = []
    monkeypatch.setattr(model.io.exr, "_read_coalesced", lambda *args: decoded.append(args))
    for layout in ("blender-cycles", "generic"):
        response = api.post("/datasets/live/sequences/cam/frames", content=blender_like_bomb(1024, 1024),
                            headers={"Content-Type": "image/x-exr"}, params={"layout": layout})
        assert response.status_code == 413, response.text
        error = response.json()["error"]
        assert error["code"] == "frame_too_large"
        assert error["message"].startswith("frame upload to live/cam: declares 1024x1024 = 1048576 pixels; the "
                                           "limit is 1024")
    assert api.get("/datasets/live/sequences/cam/frames").status_code == 404
    # An archive in the layout: refused from the headers before the conversion reads a frame.
    (folder / "frame_0002.exr").write_bytes(blender_like_bomb(1024, 1024, pass_size=(32, 32)))
    response = upload(api, make_archive(tmp_path / "up", prefix=""), name="bomb", layout="blender-cycles")
    assert response.status_code == 413, response.text
    error = response.json()["error"]
    assert error["code"] == "frame_too_large" and error["details"]["path"] == "orbit/frame_0002.exr"
    assert "in part 'ViewLayer.Depth'" in error["message"]
    assert decoded == []
    assert not (storage.datasets / "bomb").exists()


def test_a_frame_upload_decoding_past_the_limit_is_413_before_decoding(make_app, storage, tmp_path, make_archive,
                                                                       monkeypatch):
    import model.io.exr
    from tests.builders import aov_bomb

    api = TestClient(make_app(datasets.router, max_decoded_frame_bytes=16 * 8 * 127 * 4 - 1))

    def decode(*args):
        raise AssertionError("decoded")

    monkeypatch.setattr(model.io.exr, "_read_coalesced", decode)
    response = api.post("/datasets/live/sequences/cam/frames", content=aov_bomb(16, 8),
                        headers={"Content-Type": "image/x-exr"})
    assert response.status_code == 413, response.text
    error = response.json()["error"]
    assert error["code"] == "frame_too_large"
    assert error["message"].startswith("frame upload to live/cam: decodes to 65024 bytes")
    assert error["details"]["decoded_bytes"] == 65024 and error["details"]["limit_bytes"] == 65023
    # The same file in an archive: refused from its header before the archive's frames are read.
    (tmp_path / "up" / "seq").mkdir(parents=True)
    (tmp_path / "up" / "seq" / "frame_0000.exr").write_bytes(aov_bomb(16, 8))
    response = upload(api, make_archive(tmp_path / "up", prefix=""), name="bomb")
    assert response.status_code == 413, response.text
    error = response.json()["error"]
    assert error["details"] == {"path": "seq/frame_0000.exr", "decoded_bytes": 65024, "limit_bytes": 65023}
    assert not (storage.datasets / "bomb").exists()
