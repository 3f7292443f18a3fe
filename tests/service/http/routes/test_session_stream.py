"""GET /sessions/{id}/stream (WebSocket): the same outputs as POST /sessions/{id}/frames, errors that leave the
socket usable, and the REST API's authentication."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from model.io.exr import decode_image_exr, encode_frame_exr
from client.codec import decode_output, encode_bundle, encode_frame
from tests.service.session_fixtures import (  # noqa: F401 (api: a fixture)
    MODEL_NAME,
    api,
    create,
    post_frame,
    stream_frames,
)

API_KEY = "0123456789abcdef0123"


def post_outputs(client: TestClient, frames, **body) -> list[np.ndarray]:
    """Each frame's output over POST, in a new session."""
    session = create(client, **body)
    outputs = []
    for frame in frames:
        response = post_frame(client, session["id"], frame)
        assert response.status_code == 200, response.text
        outputs.append(decode_image_exr(response.content))
    return outputs


def stream_error(socket, code: str, frame_index=None) -> str:
    """The text message answering a refused frame: its message, after checking its code and frame index."""
    answer = json.loads(socket.receive_text())
    assert answer["error"]["code"] == code, answer
    assert answer["frame_index"] == frame_index
    return answer["error"]["message"]


def rounded_to_half(frame):
    """The frame with every buffer rounded to float16, as a float16 message carries it."""
    return dataclasses.replace(frame, **{name: array.astype(np.float16).astype(np.float32)
                                         for name, array in frame.render_buffers().items()})


@pytest.mark.parametrize("body", [{"version": "2"}, {"model": "accumulation", "scale": 2}],
                         ids=["registered-jnds", "accumulation"])
def test_stream_outputs_equal_the_post_outputs_exactly(api, body):
    client, _ = api()
    frames = stream_frames(6, seed=5, cuts=(4,))
    expected = post_outputs(client, frames, **body)
    session = create(client, **body)
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        for index, frame in enumerate(frames):
            socket.send_bytes(encode_bundle(frame))
            output = decode_output(socket.receive_bytes())
            np.testing.assert_array_equal(output.image, expected[index])
            header = output.header
            assert (header["frame_index"], header["width"], header["height"], header["dtype"]) == (index, 32, 32,
                                                                                                   "float32")
            assert header["history"] == {0: "started", 4: "reset-camera-cut"}.get(index, "continued")
            assert 0 < header["inference_ms"] <= header["server_ms"] and header["sanitized_pixels"] == 0
    state = client.get(f"/sessions/{session['id']}").json()
    assert (state["frames_processed"], state["next_frame_index"]) == (6, 6)


def test_float16_messages(api):
    """A float16 frame is the float32 frame rounded to half, exactly; a float16 output is the float32 output
    rounded to half, exactly (so within 2**-11 relative of it)."""
    client, _ = api()
    frames = stream_frames(4, seed=9)
    expected = post_outputs(client, [rounded_to_half(frame) for frame in frames], version="2")
    session = create(client, version="2")
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        for index, frame in enumerate(frames):
            socket.send_bytes(encode_bundle(frame, dtype="float16", output_dtype="float16" if index % 2 else
                                            "float32"))
            output = decode_output(socket.receive_bytes())
            if index % 2:
                assert output.header["dtype"] == "float16"
                np.testing.assert_array_equal(output.image, expected[index].astype(np.float16).astype(np.float32))
                np.testing.assert_allclose(output.image, expected[index], rtol=2.0 ** -11, atol=1e-7)
            else:
                np.testing.assert_array_equal(output.image, expected[index])


def test_optional_buffers_may_be_left_out_and_the_index_left_to_the_session(api):
    client, _ = api()
    frames = [dataclasses.replace(frame, diffuse=None, specular=None) for frame in stream_frames(3, seed=2)]
    expected = post_outputs(client, frames, version="1")
    session = create(client, version="1")
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        for index, frame in enumerate(frames):
            socket.send_bytes(encode_bundle(frame, frame_index=None if index else True))
            output = decode_output(socket.receive_bytes())
            assert output.frame_index == index
            np.testing.assert_array_equal(output.image, expected[index])


def _with_buffers(frame, **buffers) -> bytes:
    values = {name: getattr(frame, name) for name in ("color", "albedo", "normal", "depth", "motion")}
    values.update(buffers)
    return encode_frame({k: v for k, v in values.items() if v is not None}, frame_index=frame.frame_index,
                        jitter=frame.jitter)


def test_bad_frames_are_answered_with_an_error_and_the_stream_goes_on(api):
    client, _ = api(max_frame_bytes=200_000, max_frame_pixels=400)
    frames = stream_frames(4, seed=1)
    plain = [dataclasses.replace(frame, diffuse=None, specular=None) for frame in frames]
    expected = post_outputs(client, plain, version="2", on_gap="reject")
    session = create(client, version="2", on_gap="reject")
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        socket.send_bytes(encode_bundle(plain[0]))
        np.testing.assert_array_equal(decode_output(socket.receive_bytes()).image, expected[0])

        good = encode_bundle(plain[1])
        socket.send_bytes(b"GIF89a" + good[6:])
        assert "not the magic b'DNST'" in stream_error(socket, "invalid_message")
        socket.send_bytes(good[:-4])
        assert "the header declares 16x16 pixels" in stream_error(socket, "invalid_frame")
        socket.send_text("hello")
        assert "binary" in stream_error(socket, "invalid_message")
        socket.send_bytes(_with_buffers(plain[1], depth=None))
        assert "required buffer 'depth' is missing" in stream_error(socket, "invalid_frame")
        socket.send_bytes(_with_buffers(plain[1], normal=plain[1].normal * 2))
        assert "buffer 'normal'" in stream_error(socket, "invalid_frame", 1)
        socket.send_bytes(encode_bundle(stream_frames(1, size=24, start=1)[0]))
        assert "the limit is 400 pixels" in stream_error(socket, "frame_too_large", None)
        socket.send_bytes(encode_bundle(stream_frames(1, size=8, start=1)[0]))
        assert "8x8 but this session's frames are 16x16" in stream_error(socket, "resolution_mismatch", 1)
        socket.send_bytes(encode_bundle(plain[0]))
        assert "frame_index 0 repeats" in stream_error(socket, "frame_out_of_order", 0)
        socket.send_bytes(encode_bundle(plain[3]))
        assert "expects frame_index 1" in stream_error(socket, "frame_gap", 3)
        socket.send_bytes(b"\0" * 200_001)
        assert "the limit is 200000 bytes" in stream_error(socket, "payload_too_large")

        for frame, output in zip(plain[1:], expected[1:]):  # the history was kept through all of it
            socket.send_bytes(encode_bundle(frame))
            np.testing.assert_array_equal(decode_output(socket.receive_bytes()).image, output)


def test_nan_and_negative_radiance_are_repaired_and_reported_as_over_post(api):
    client, _ = api()
    frame = stream_frames(1, seed=4)[0]
    color = frame.color.copy()
    color[0, 0], color[1, 1, 2] = np.nan, -1.0
    broken = dataclasses.replace(frame, color=color, diffuse=None, specular=None)
    session = create(client, version="2")
    response = client.post(f"/sessions/{session['id']}/frames", content=encode_frame_exr(broken, sanitizable=True))
    assert response.status_code == 200, response.text
    other = create(client, version="2")
    with client.websocket_connect(f"/sessions/{other['id']}/stream") as socket:
        socket.send_bytes(encode_bundle(broken))
        output = decode_output(socket.receive_bytes())
    assert output.header["sanitized_pixels"] == int(response.headers["x-sanitized-pixels"]) == 2
    assert output.header["sanitized"] == response.headers["x-sanitized"]
    np.testing.assert_array_equal(output.image, decode_image_exr(response.content))


def _closed(client: TestClient, path: str, headers: dict | None = None) -> WebSocketDisconnect:
    with client.websocket_connect(path, headers=headers or {}) as socket:
        with pytest.raises(WebSocketDisconnect) as closed:
            socket.receive_bytes()
    return closed.value


def test_unknown_and_deleted_sessions_close_with_4404(api):
    client, _ = api()
    closed = _closed(client, "/sessions/0123456789abcdef0123456789abcdef/stream")
    assert closed.code == 4404 and closed.reason.startswith("not_found: session '0123456789abcdef")
    assert _closed(client, "/sessions/not-an-id/stream").code == 4404

    session = create(client, version="2")
    frames = stream_frames(2)
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        socket.send_bytes(encode_bundle(frames[0]))
        socket.receive_bytes()
        assert client.delete(f"/sessions/{session['id']}").status_code == 204
        socket.send_bytes(encode_bundle(frames[1]))
        with pytest.raises(WebSocketDisconnect) as closed:
            socket.receive_bytes()
    assert closed.value.code == 4404 and "does not exist" in closed.value.reason


def test_the_api_key_and_the_owner_token_are_required_as_over_http(api):
    client, _ = api(api_key=API_KEY, session_owner_tokens=True)
    key = {"X-API-Key": API_KEY}
    response = client.post("/sessions", json={"model": MODEL_NAME, "version": "2"}, headers=key)
    assert response.status_code == 201, response.text
    session = response.json()
    path = f"/sessions/{session['id']}/stream"
    closed = _closed(client, path)
    assert closed.code == 4401 and closed.reason.startswith("unauthorized: missing X-API-Key")
    assert _closed(client, path, {"X-API-Key": "wrong"}).code == 4401
    closed = _closed(client, path, key)
    assert closed.code == 4403 and closed.reason.startswith("session_forbidden")
    assert _closed(client, path, {**key, "X-Session-Token": "not-the-token"}).code == 4403
    with client.websocket_connect(path, headers={**key, "X-Session-Token": session["token"]}) as socket:
        socket.send_bytes(encode_bundle(stream_frames(1)[0]))
        assert decode_output(socket.receive_bytes()).frame_index == 0


def test_frames_sent_ahead_are_answered_in_order_as_one_at_a_time(api):
    """A client may send frames before their outputs arrive (the server reads the next one while the one before
    steps): the answers are the same, in the same order, a refused frame's error in its place."""
    client, _ = api()
    frames = stream_frames(4, seed=3)
    expected = post_outputs(client, frames, version="2", on_gap="reject")
    session = create(client, version="2", on_gap="reject")
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        for message in [*map(encode_bundle, frames[:2]), b"not a frame", *map(encode_bundle, frames[2:])]:
            socket.send_bytes(message)
        for index in (0, 1):
            output = decode_output(socket.receive_bytes())
            assert output.frame_index == index
            np.testing.assert_array_equal(output.image, expected[index])
        assert "shorter than the 12-byte prelude" in stream_error(socket, "invalid_message")
        for index in (2, 3):
            output = decode_output(socket.receive_bytes())
            assert output.frame_index == index and output.header["history"] == "continued"
            np.testing.assert_array_equal(output.image, expected[index])
    assert client.get(f"/sessions/{session['id']}").json()["frames_processed"] == 4


def test_a_client_gone_with_frames_in_flight_leaves_the_frame_budget_free_and_the_session_usable(api):
    import time

    from service.http.request_limits import frame_budget

    capacity = 3_000_000  # a budget of this test's own (budgets are shared per capacity)
    client, _ = api(max_buffered_frame_bytes=capacity)
    budget = frame_budget(capacity)
    frames = stream_frames(4, seed=12)
    session = create(client, version="2")
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        for frame in frames[:3]:
            socket.send_bytes(encode_bundle(frame))
    deadline = time.monotonic() + 30
    while budget.held:  # the frames read ahead are freed once the handler is done with them
        assert time.monotonic() < deadline, f"{budget.held} bytes still held"
        time.sleep(0.02)
    # How many of them stepped depends on when the handler learnt the client was gone; the session goes on.
    with client.websocket_connect(f"/sessions/{session['id']}/stream") as socket:
        socket.send_bytes(encode_bundle(frames[3], frame_index=None))
        assert decode_output(socket.receive_bytes()).frame_index in range(4)
