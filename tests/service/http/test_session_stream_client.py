"""client.rest.DenoiserClient.open_stream and `denoiser stream` (WebSocket by default) against the API's session
WebSocket served by uvicorn (here, beside the /sessions fixtures it needs)."""

from __future__ import annotations

import dataclasses
import threading
import time

import httpx
import numpy as np
import pytest

from service.http.routes import models as models_routes
from service.http.routes import session_stream
from service.http.routes import sessions as sessions_routes
from service.sessions.store import get_session_store
from cli.main import main
from client.frames import BUFFER_COMPONENTS
from client.rest import ApiClientError, DenoiserClient, ServerUnreachable
from client.stream import websocket_url
from model.io.dataset import SequenceWriter
from model.io.exr import decode_image_exr
from tests.service.session_fixtures import MODEL_NAME, shared_registry, stream_frames
from tests.builders import closed_port

API_KEY = "0123456789abcdef0123"


@pytest.fixture
def serve(make_app, make_store):
    """``serve(**setting_changes)`` -> the URL of /sessions, its WebSocket and /models served by uvicorn in a
    thread, on a store of this test (stopped at the end of the test)."""
    import uvicorn

    servers = []

    def start(**changes) -> str:
        store = make_store(**changes)
        app = make_app(sessions_routes.router, models_routes.router, public=(session_stream.router,),
                       tracking_uri=shared_registry().uri, **changes)
        app.dependency_overrides[get_session_store] = lambda: store
        port = closed_port()
        server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
        thread = threading.Thread(target=server.run, daemon=True)
        thread.start()
        servers.append((server, thread))
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 30
        while not server.started:
            assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.02)
        return url

    yield start
    for server, thread in servers:
        server.should_exit = True
        thread.join(10)


def test_open_stream_gives_what_send_frame_gives(serve):
    url = serve()
    frames = stream_frames(5, seed=11, cuts=(3,))
    with DenoiserClient(url) as client:
        posted = client.create_session(MODEL_NAME, version="2")
        expected = [client.send_frame(posted["id"], frame) for frame in frames]
        session = client.create_session(MODEL_NAME, version="2")
        with client.open_stream(session["id"]) as stream:
            for frame, (image, post_info) in zip(frames, expected):
                output, info = stream.send(frame)
                np.testing.assert_array_equal(output, image)
                assert (info.frame_index, info.history, info.sanitized_pixels) == (post_info.frame_index,
                                                                                   post_info.history, 0)
                assert 0 < info.inference_ms <= info.server_ms < info.round_trip_ms
                assert info.headers["X-History"] == post_info.headers["X-History"]
        assert client.get_session(session["id"])["frames_processed"] == 5
        # A renderer's arrays, no file: over HTTP (an in-memory EXR) and over the WebSocket, the same outputs.
        arrays = [{name: getattr(frame, name) for name in BUFFER_COMPONENTS if getattr(frame, name) is not None}
                  | {"jitter": frame.jitter, "camera_cut": frame.camera_cut} for frame in frames]
        by_post = client.create_session(MODEL_NAME, version="2")
        by_socket = client.create_session(MODEL_NAME, version="2")
        with client.open_stream(by_socket.id) as stream:
            for given, (image, _) in zip(arrays, expected):
                posted_image, info = client.send_arrays(by_post.id, **given)
                streamed_image, _ = stream.send_arrays(**given)
                np.testing.assert_array_equal(posted_image, image)
                np.testing.assert_array_equal(streamed_image, image)
        assert by_socket.model.name == MODEL_NAME and client.get_session(by_post.id).frames_processed == 5


def test_a_stream_sends_only_the_buffers_the_sessions_method_reads(serve, monkeypatch):
    from client import codec as stream_codec

    url = serve()
    frames = stream_frames(3, seed=5)
    assert frames[0].diffuse is not None and frames[0].specular is not None  # what a lean stream leaves out
    sent = []
    encode = stream_codec.encode_frame
    monkeypatch.setattr(stream_codec, "encode_frame", lambda buffers, **kw: sent.append(sorted(buffers)) or encode(
        buffers, **kw))
    with DenoiserClient(url) as client:
        posted = client.create_session("accumulation")
        expected = [client.send_frame(posted["id"], frame)[0] for frame in frames]
        session = client.create_session("accumulation")
        assert session["model"]["buffers"] == ["color", "albedo", "normal", "depth", "motion"]
        with client.open_stream(session["id"]) as lean, client.open_stream(
                client.create_session("accumulation")["id"], all_buffers=True) as full:
            assert lean.buffers == tuple(session["model"]["buffers"]) and full.buffers is None
            for frame, image in zip(frames, expected):
                np.testing.assert_array_equal(lean.send(frame)[0], image)
                np.testing.assert_array_equal(full.send(frame)[0], image)
    assert sent[0] == sorted(session["model"]["buffers"])
    assert {"diffuse", "specular"} <= set(sent[1])


def test_a_refused_frame_raises_and_the_stream_goes_on(serve):
    url = serve()
    frames = stream_frames(3, seed=2)
    with DenoiserClient(url) as client:
        session = client.create_session(MODEL_NAME, version="1", on_gap="reject")
        with client.open_stream(session["id"], dtype="float16", output_dtype="float16") as stream:
            assert stream.send(frames[0])[1].frame_index == 0
            with pytest.raises(ApiClientError) as refused:
                stream.send(frames[2])
            assert (refused.value.status, refused.value.code) == (409, "frame_gap")
            with pytest.raises(ApiClientError) as refused:
                stream.send(b"not a frame")
            assert (refused.value.status, refused.value.code) == (400, "invalid_message")
            output, info = stream.send(frames[1])
            assert info.frame_index == 1 and info.history == "continued" and output.dtype == np.float32


def test_send_many_keeps_frames_in_flight_and_gives_what_send_gives(serve):
    url = serve()
    frames = stream_frames(6, seed=4)
    with DenoiserClient(url) as client:
        one_by_one = client.create_session(MODEL_NAME, version="2", on_gap="reject")
        with client.open_stream(one_by_one["id"]) as stream:
            expected = [stream.send(frame)[0] for frame in frames]
        session = client.create_session(MODEL_NAME, version="2", on_gap="reject")
        with client.open_stream(session["id"]) as stream:
            results = list(stream.send_many(frames[:4], in_flight=3))
            assert [info.frame_index for _, info in results] == [0, 1, 2, 3]
            for (output, info), image in zip(results, expected):
                np.testing.assert_array_equal(output, image)
                assert 0 < info.inference_ms <= info.server_ms < info.round_trip_ms
            # A refused frame raises after the frames before it; those sent after it are answered and dropped,
            # and the stream goes on.
            gap = dataclasses.replace(frames[5], frame_index=9)
            given = stream.send_many([frames[4], gap, frames[5]], in_flight=3)
            np.testing.assert_array_equal(next(given)[0], expected[4])
            with pytest.raises(ApiClientError) as refused:
                next(given)
            assert (refused.value.status, refused.value.code) == (409, "frame_gap")
            assert client.get_session(session["id"])["frames_processed"] == 6
            with pytest.raises(ValueError, match="in_flight"):
                next(stream.send_many(frames, in_flight=0))


def test_stream_errors_that_end_the_stream(serve):
    url = serve(api_key=API_KEY, session_owner_tokens=True)
    frame = stream_frames(1)[0]
    with DenoiserClient(url, api_key=API_KEY) as client:
        session = client.create_session(MODEL_NAME, version="2")
        with client.open_stream(session["id"]) as stream:  # the key and the owner token go along
            assert stream.send(frame)[1].frame_index == 0
        with DenoiserClient(url, api_key=API_KEY) as stranger:  # no token
            with stranger.open_stream(session["id"]) as stream, pytest.raises(ApiClientError) as refused:
                stream.send(frame)
            assert (refused.value.status, refused.value.code) == (403, "session_forbidden")
        with DenoiserClient(url) as keyless:
            with keyless.open_stream(session["id"]) as stream, pytest.raises(ApiClientError) as refused:
                stream.send(frame)
            assert (refused.value.status, refused.value.code) == (401, "unauthorized")
        with client.open_stream("0" * 32) as stream, pytest.raises(ApiClientError) as refused:
            stream.send(frame)
        assert (refused.value.status, refused.value.code) == (404, "not_found")
    with pytest.raises(ServerUnreachable, match="ws://127.0.0.1"):
        DenoiserClient(f"http://127.0.0.1:{closed_port()}").open_stream(session["id"])
    assert websocket_url("https://gpu-box:8443/api", "/x") == "wss://gpu-box:8443/api/x"


def test_with_owner_tokens_a_client_lists_the_sessions_it_created(serve):
    url = serve(api_key=API_KEY, session_owner_tokens=True)
    with DenoiserClient(url, api_key=API_KEY) as client, DenoiserClient(url, api_key=API_KEY) as other:
        mine = {client.create_session(MODEL_NAME, version="2")["id"] for _ in range(2)}
        theirs = other.create_session(MODEL_NAME, version="2")["id"]
        assert {session["id"] for session in client.list_sessions()} == mine
        assert [session["id"] for session in other.list_sessions()] == [theirs]
        with DenoiserClient(url, api_key=API_KEY) as stranger:
            assert stranger.list_sessions() == []


def test_denoiser_stream_uses_the_websocket_by_default(serve, tmp_path, capsys):
    url = serve()
    sequence = tmp_path / "seq"
    with SequenceWriter(sequence, "seq") as writer:
        for frame in stream_frames(3, seed=6):
            writer.add(dataclasses.replace(frame, sequence="seq"))
    for transport in ("websocket", "http"):
        argv = ["stream", str(sequence), "--model", "accumulation", "--scale", "2", "--url", url, "--out",
                str(tmp_path / transport)]
        assert main(argv + (["--transport", "http"] if transport == "http" else [])) == 0
    out = capsys.readouterr().out
    assert "3 frames in" in out and "history: started 1, continued 2" in out
    for index in range(3):
        name = f"frame_{index:04d}.exr"
        np.testing.assert_array_equal(decode_image_exr((tmp_path / "websocket" / name).read_bytes()),
                                      decode_image_exr((tmp_path / "http" / name).read_bytes()))
    assert httpx.get(f"{url}/sessions").json() == []  # both sessions deleted


def test_stream_sequence_over_the_websocket_stops_at_a_refused_frame_after_writing_the_ones_before(serve, tmp_path):
    url = serve()
    from model.io.exr import encode_frame_exr

    sequence = tmp_path / "renders"  # a renderer's plain folder: its files are sent as they are
    sequence.mkdir()
    for frame in [frame for frame in stream_frames(5, seed=8) if frame.frame_index != 2]:  # a gap it refuses
        (sequence / f"render_{frame.frame_index:04d}.exr").write_bytes(encode_frame_exr(frame))
    with DenoiserClient(url) as client:
        session = client.create_session(MODEL_NAME, version="2", on_gap="reject")
        with pytest.raises(ApiClientError) as refused:
            client.stream_sequence(session["id"], sequence, tmp_path / "out", transport="websocket")
        assert (refused.value.status, refused.value.code) == (409, "frame_gap")
        assert sorted(path.name for path in (tmp_path / "out").iterdir()) == ["frame_0000.exr", "frame_0001.exr"]
        assert client.get_session(session["id"])["frames_processed"] == 2
