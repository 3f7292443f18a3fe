"""client.frames and client.answers: the client's frame files are the model library's, byte for meaning, and its
answers read as typed objects and as the dicts they were."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import OpenEXR
import pytest

from client.answers import Job, Model, Session
from client.frames import (
    BUFFER_COMPONENTS,
    REQUIRED_BUFFERS,
    FrameFileError,
    as_frame,
    decode_image_exr,
    encode_frame_exr,
    encode_png,
    make_frame,
    read_frame_exr,
    renderer_frame_files,
    sequence_frame_files,
)
from model.io.exr import encode_image_exr as model_encode_image, read_frame_bytes, write_frame
from model.io.frames import BUFFERS, RENDER_BUFFERS
from tests.builders import make_frame as model_frame


def test_the_buffer_table_is_the_frame_bundles():
    assert tuple(BUFFER_COMPONENTS) == RENDER_BUFFERS
    assert {name: "".join(BUFFERS[name].components) for name in RENDER_BUFFERS} == BUFFER_COMPONENTS
    assert REQUIRED_BUFFERS == tuple(name for name in RENDER_BUFFERS if BUFFERS[name].required)


def test_client_frames_and_library_frames_read_each_other(tmp_path):
    bundle = model_frame(0, scales=(1, 2))
    # library file -> client: the render buffers and header, the references left out
    frame = read_frame_exr(write_frame(tmp_path / "f.exr", bundle))
    for name in ("color", "albedo", "normal", "depth", "motion"):
        np.testing.assert_array_equal(frame.buffers[name], getattr(bundle, name))
    assert (frame.jitter, frame.frame_index, frame.sequence) == (bundle.jitter, bundle.frame_index, bundle.sequence)
    # client bytes -> library: a valid frame bundle with the same values
    again = read_frame_bytes(encode_frame_exr(frame, compression="zip"))
    np.testing.assert_array_equal(again.depth, bundle.depth)
    assert (again.jitter, again.frame_index, again.scales) == (bundle.jitter, bundle.frame_index, ())
    assert as_frame(bundle).buffers.keys() == frame.buffers.keys()


def test_make_frame_names_a_wrong_buffer():
    h, w = 2, 3
    good = dict(color=np.zeros((h, w, 3)), albedo=np.zeros((h, w, 3)), normal=np.zeros((h, w, 3)),
                depth=np.zeros((h, w, 1)), motion=np.zeros((h, w, 2)))
    assert make_frame(**good).buffers["depth"].shape == (h, w)  # (H, W, 1) accepted as (H, W)
    with pytest.raises(FrameFileError, match="buffer 'motion' has shape \\(2, 3, 3\\), expected \\(2, 3, 2\\)"):
        make_frame(**{**good, "motion": np.zeros((h, w, 3))})
    with pytest.raises(FrameFileError, match="unknown buffer\\(s\\) alpha"):
        make_frame(**good, alpha=np.zeros((h, w)))
    with pytest.raises(FrameFileError, match="not an OpenEXR file"):
        read_frame_exr(b"not an exr")


def test_a_frame_without_jitter_reads_as_zero_and_one_without_a_buffer_is_named(tmp_path):
    h, w = 2, 3
    planes = {f"{name}.{c}": np.full((h, w), 0.5, np.float32) for name, components in BUFFER_COMPONENTS.items()
              if name in REQUIRED_BUFFERS for c in components}
    path = str(tmp_path / "live.exr")
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}, dict(planes)).write(path)
    frame = read_frame_exr(path)
    assert (frame.jitter, frame.frame_index, frame.width, frame.height) == ((0.0, 0.0), None, w, h)
    del planes["motion.Y"]
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}, planes).write(path)
    with pytest.raises(FrameFileError, match="buffer 'motion' lacks channel\\(s\\) motion.Y"):
        read_frame_exr(path)


def test_output_images_and_their_display_png():
    rgb = np.array([[[0.0, 0.5, 1.0], [2.0, -1.0, 0.25]]], np.float32)
    np.testing.assert_array_equal(decode_image_exr(model_encode_image(rgb)), rgb)
    pixels = _read_png(encode_png(rgb))
    expected = np.round(np.clip(rgb, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)
    np.testing.assert_array_equal(pixels, expected)
    assert pixels[0, 0].tolist() == [0, 186, 255] and pixels[0, 1].tolist() == [255, 0, 136]  # 0.5 -> 186


def _read_png(data: bytes) -> np.ndarray:
    """An 8-bit RGB PNG's pixels, every chunk's CRC checked (rows filtered with type 0, as encode_png writes)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    offset, chunks = 8, {}
    while offset < len(data):
        (length,), kind = struct.unpack(">I", data[offset:offset + 4]), data[offset + 4:offset + 8]
        body = data[offset + 8:offset + 8 + length]
        assert struct.unpack(">I", data[offset + 8 + length:offset + 12 + length])[0] == zlib.crc32(kind + body)
        chunks[kind] = chunks.get(kind, b"") + body
        offset += 12 + length
    width, height, depth, color_type = struct.unpack(">IIBB", chunks[b"IHDR"][:10])
    assert (depth, color_type, b"IEND" in chunks) == (8, 2, True)
    rows = np.frombuffer(zlib.decompress(chunks[b"IDAT"]), np.uint8).reshape(height, 1 + width * 3)
    assert not rows[:, 0].any()
    return rows[:, 1:].reshape(height, width, 3)


def test_only_this_projects_manifest_makes_a_sequence_folder(tmp_path):
    (tmp_path / "b.exr").write_bytes(b"")
    (tmp_path / "a.exr").write_bytes(b"")
    (tmp_path / "manifest.json").write_text(json.dumps({"format": None, "renderer": "blender", "frames": 2}))
    (tmp_path / "preview.jpg").write_bytes(b"")
    files, ignored = renderer_frame_files(tmp_path)
    assert [p.name for p in files] == ["a.exr", "b.exr"] and ignored == ["manifest.json", "preview.jpg"]
    with pytest.raises(FrameFileError, match="not a readable sequence manifest"):
        sequence_frame_files(tmp_path)


def test_answers_are_typed_and_still_read_as_dicts():
    job = Job.from_dict({"id": "j1", "state": "running", "progress": {"current": 2, "total": 4, "message": "m",
                                                                     "eta_seconds": None}, "future_field": 1})
    assert (job.id, job.state, job.progress.current, job.error) == ("j1", "running", 2, None)
    assert job["progress"]["total"] == 4 and job.get("future_field") == 1 and "future_field" in job
    assert job == {"id": "j1", "state": "running", "progress": {"current": 2, "total": 4, "message": "m",
                                                                "eta_seconds": None}, "future_field": 1}
    assert json.loads(json.dumps(job.to_dict()))["id"] == "j1"
    session = Session.from_dict({"id": "s", "model": {"name": "m", "buffers": ["color"]}})
    assert session.model.buffers == ["color"] and session.token is None
    model = Model.from_dict({"name": "m", "versions": [{"version": "2", "ref": "models:/m/2"}]})
    assert model.versions[0].ref == "models:/m/2" and model["versions"][0]["version"] == "2"
