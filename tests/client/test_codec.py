"""client.codec: the session stream's messages round-trip, and malformed ones say what is wrong."""

from __future__ import annotations

import json
import struct
import subprocess
import sys

import numpy as np
import pytest

from client.codec import (
    ALIGNMENT,
    PRELUDE,
    STREAM_BUFFERS,
    StreamMessageError,
    decode_frame,
    decode_output,
    encode_bundle,
    encode_frame,
    encode_output,
)
from tests.builders import synthetic_frame


def frames(count: int = 1, start: int = 0, size: int = 16) -> list:
    rng = np.random.default_rng(3)
    return [synthetic_frame(rng, start + index, size, size) for index in range(count)]


def message(header: dict, payload: bytes = b"", kind: int = 1, magic: bytes = b"DNST", version: int = 1) -> bytes:
    text = json.dumps(header).encode()
    return PRELUDE.pack(magic, version, kind, 0, len(text)) + text + payload


def frame_header(**changes) -> dict:
    header = {"frame_index": 3, "width": 2, "height": 1, "dtype": "float32",
              "buffers": ["color", "albedo", "normal", "depth", "motion"], "jitter": [0.25, -0.5]}
    header.update(changes)
    return {key: value for key, value in header.items() if value is not ...}


def test_a_bundle_sends_only_the_buffers_asked_for_and_the_required_ones():
    frame = frames()[0]
    assert frame.diffuse is not None and frame.specular is not None
    lean = decode_frame(encode_bundle(frame, buffers=(name for name in ["roughness", "diffuse", "specular"])))
    assert list(lean.buffers) == ["color", "albedo", "diffuse", "specular", "normal", "depth", "motion"]
    np.testing.assert_array_equal(lean.hwc("diffuse"), frame.diffuse)
    assert list(decode_frame(encode_bundle(frame, buffers=())).buffers) == ["color", "albedo", "normal", "depth",
                                                                             "motion"]


@pytest.mark.parametrize("dtype", ["float32", "float16"])
def test_a_frame_bundle_round_trips(dtype):
    frame = frames(start=7)[0]
    data = encode_bundle(frame, dtype=dtype, output_dtype="float16")
    decoded = decode_frame(data)
    assert (decoded.frame_index, decoded.width, decoded.height, decoded.dtype) == (7, 16, 16, dtype)
    assert decoded.jitter == frame.jitter and decoded.camera_cut is False and decoded.output_dtype == "float16"
    assert list(decoded.buffers) == [name for name in STREAM_BUFFERS if getattr(frame, name) is not None]
    for name in decoded.buffers:
        expected = getattr(frame, name).astype(dtype)
        np.testing.assert_array_equal(decoded.hwc(name), expected)
        assert decoded.buffers[name].shape == ((16, 16) if expected.ndim == 2 else (expected.shape[2], 16, 16))
    header_length = struct.unpack_from("<I", data, 8)[0]
    assert (PRELUDE.size + header_length) % ALIGNMENT == 0  # the arrays start aligned
    planes = sum(1 if array.ndim == 2 else array.shape[0] for array in decoded.buffers.values())
    assert len(data) == PRELUDE.size + header_length + planes * 16 * 16 * np.dtype(dtype).itemsize


def test_the_arrays_are_planar_little_endian_in_the_listed_order():
    color = np.arange(6, dtype=np.float32).reshape(1, 2, 3)  # pixel (0, 0) = 0 1 2, pixel (1, 0) = 3 4 5
    buffers = {"color": color, "albedo": color / 10, "normal": np.zeros((1, 2, 3), np.float32),
               "depth": np.array([[7, 8]], np.float32), "motion": np.zeros((1, 2, 2), np.float32)}
    data = encode_frame(buffers, frame_index=None, jitter=(0, 0), camera_cut=True)
    header_length = struct.unpack_from("<I", data, 8)[0]
    header = json.loads(data[PRELUDE.size:PRELUDE.size + header_length])
    assert header == {"frame_index": None, "width": 2, "height": 1, "dtype": "float32",
                      "buffers": ["color", "albedo", "normal", "depth", "motion"], "jitter": [0.0, 0.0],
                      "camera_cut": True, "output_dtype": "float32"}
    values = np.frombuffer(data, "<f4", offset=PRELUDE.size + header_length)
    assert values[:6].tolist() == [0, 3, 1, 4, 2, 5]  # R plane, G plane, B plane
    assert values[18:20].tolist() == [7, 8]  # depth after color, albedo, normal (3 planes of 2 values each)
    decoded = decode_frame(data)
    assert decoded.frame_index is None and decoded.camera_cut is True


def test_an_output_round_trips():
    image = np.random.default_rng(0).uniform(0, 4, size=(4, 6, 3)).astype(np.float32)
    for dtype in ("float32", "float16"):
        data = encode_output(image, dtype=dtype, frame_index=5, server_ms=1.5, inference_ms=1.0, history="continued",
                             sanitized_pixels=0)
        output = decode_output(data)
        assert output.header == {"frame_index": 5, "width": 6, "height": 4, "dtype": dtype, "server_ms": 1.5,
                                 "inference_ms": 1.0, "history": "continued", "sanitized_pixels": 0}
        assert output.image.dtype == np.float32
        np.testing.assert_array_equal(output.image, image.astype(dtype).astype(np.float32))
    with pytest.raises(StreamMessageError, match="where a output"):
        decode_output(encode_bundle(frames()[0]))


def _payload(planes: int, pixels: int = 2, dtype: str = "<f4") -> bytes:
    return np.zeros(planes * pixels, dtype).tobytes()


@pytest.mark.parametrize("data, code, text", [
    (b"DNST", "invalid_message", "shorter than the 12-byte prelude"),
    (message(frame_header(), magic=b"\x89PNG"), "invalid_message", "not the magic b'DNST'"),
    (message(frame_header(), version=2), "unsupported_version", "protocol version 2 is not supported"),
    (message(frame_header(), kind=2), "invalid_message", "message kind 2 (output) where a frame"),
    (PRELUDE.pack(b"DNST", 1, 1, 0, 500) + b"{}", "invalid_message", "the header length is 500 bytes but only 2"),
    (PRELUDE.pack(b"DNST", 1, 1, 0, 3) + b"{x}", "invalid_message", "the header is not JSON"),
    (message([1, 2]), "invalid_message", "a JSON list, not an object"),
    (message(frame_header(colour="red")), "invalid_message", "unknown header field(s) colour"),
    (message(frame_header(width=0)), "invalid_message", "'width' is 0; expected an integer >= 1"),
    (message(frame_header(frame_index=-1)), "invalid_message", "'frame_index' is -1"),
    (message(frame_header(frame_index=True)), "invalid_message", "'frame_index' is True"),
    (message(frame_header(dtype="float64")), "invalid_message", "'dtype' is 'float64'; expected one of float16"),
    (message(frame_header(output_dtype="int8")), "invalid_message", "'output_dtype' is 'int8'"),
    (message(frame_header(buffers="color")), "invalid_message", "expected a list of buffer names"),
    (message(frame_header(buffers=["color", "albedo", "normal", "depth", "motion", "reference"])), "invalid_message",
     "unknown buffer(s) 'reference'"),
    (message(frame_header(buffers=["color", "color", "albedo", "normal", "depth", "motion"])), "invalid_message",
     "color listed more than once"),
    (message(frame_header(buffers=["color", "albedo", "normal", "motion"])), "invalid_frame",
     "required buffer 'depth' is missing"),
    (message(frame_header(jitter=[0.1])), "invalid_message", "'jitter' is [0.1]; expected [x, y]"),
    (message(frame_header(camera_cut=1)), "invalid_message", "'camera_cut' is 1; expected true or false"),
    (message(frame_header(), _payload(11)), "invalid_frame",
     "the arrays are 88 bytes; the header declares 2x1 pixels of color 3 + albedo 3 + normal 3 + depth 1 + "
     "motion 2 = 12 float32 planes = 96 bytes"),
    (message(frame_header(dtype="float16"), _payload(12)), "invalid_frame", "= 48 bytes"),
])
def test_malformed_frames_are_refused_naming_the_problem(data, code, text):
    with pytest.raises(StreamMessageError) as refused:
        decode_frame(data)
    assert refused.value.code == code
    assert text in refused.value.message


def test_a_valid_hand_made_message_decodes_and_the_pixel_limit_is_checked_first():
    data = message(frame_header(), _payload(12))
    assert decode_frame(data).buffers["motion"].shape == (2, 1, 2)
    with pytest.raises(StreamMessageError) as refused:
        decode_frame(message(frame_header(width=5000, height=5000)), max_pixels=1000)
    assert refused.value.code == "frame_too_large" and refused.value.details["limit_pixels"] == 1000


def test_encoding_refuses_what_it_cannot_send():
    frame = frames()[0]
    with pytest.raises(ValueError, match="dtype must be one of float16, float32"):
        encode_bundle(frame, dtype="bfloat16")
    with pytest.raises(ValueError, match="unknown buffer"):
        encode_frame({"color": frame.color, "reference": frame.color}, frame_index=0, jitter=(0, 0))
    with pytest.raises(ValueError, match="buffer 'depth' is"):
        encode_frame({"color": frame.color, "depth": frame.color}, frame_index=0, jitter=(0, 0))


def test_the_codec_imports_without_torch():
    code = ("import sys, client.codec, client.rest, client.stream; "
            "assert 'torch' not in sys.modules, 'torch'")
    subprocess.run([sys.executable, "-c", code], check=True)
