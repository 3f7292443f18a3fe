"""/sessions over HTTP: a streamed sequence equals in-process inference, restore after a restart, every error."""

from __future__ import annotations

import io

import numpy as np
import OpenEXR
import pytest

from model.io.exr import _frame_parts, decode_image_exr
from tests.builders import error_message
from tests.service.session_fixtures import (  # noqa: F401 (api: a fixture)
    MODEL_NAME,
    FakeClock,
    api,
    assert_same_image,
    assert_same_image_after_half_history,
    create,
    frame_bytes,
    in_process_outputs,
    post_frame,
    shared_registry,
    stream_frames,
)

def test_a_16_frame_stream_gives_what_the_method_gives_in_process(api):
    client, _ = api()
    session = create(client, version="2")
    assert session["model"] == {"name": MODEL_NAME, "version": "2", "alias": None, "method": "jnds",
                                "preset": "xs", "scale": 2, "params": session["model"]["params"],
                                "source": "registered", "buffers": ["color", "albedo", "diffuse", "specular", "normal",
                                                                    "depth", "roughness", "motion"]}
    assert session["next_frame_index"] is None and session["resolution"] is None
    frames = stream_frames(16, seed=7)
    expected = in_process_outputs(shared_registry().checkpoints["2"], frames)
    for index, frame in enumerate(frames):
        response = post_frame(client, session["id"], frame, "application/octet-stream" if index % 2 else None)
        assert response.status_code == 200, response.text
        assert response.headers["content-type"] == "image/x-exr"
        assert response.headers["x-frame-index"] == str(index)
        assert response.headers["x-history"] == ("started" if index == 0 else "continued")
        inference, server = float(response.headers["x-inference-ms"]), float(response.headers["x-server-ms"])
        assert 0 < inference <= server
        output = decode_image_exr(response.content)
        assert output.shape == (32, 32, 3)  # scale 2
        assert_same_image(output, expected[index])
    state = client.get(f"/sessions/{session['id']}").json()
    assert (state["frames_processed"], state["next_frame_index"], state["resolution"]) == (16, 16, [16, 16])


def test_a_restarted_api_continues_the_session_from_redis(api):
    frames = stream_frames(4, seed=3)
    expected = in_process_outputs(shared_registry().checkpoints["1"], frames)
    client, _ = api()
    session = create(client, alias="champion")
    assert session["model"]["version"] == "1" and session["model"]["alias"] == "champion"
    for frame in frames[:3]:
        assert post_frame(client, session["id"], frame).status_code == 200

    restarted, store = api()  # a new store (nothing in memory) on the same Redis
    assert not store._sessions
    assert [s["id"] for s in restarted.get("/sessions").json()] == [session["id"]]
    assert restarted.get(f"/sessions/{session['id']}").json()["next_frame_index"] == 3
    response = post_frame(restarted, session["id"], frames[3])
    assert response.status_code == 200 and response.headers["x-history"] == "continued"
    assert_same_image_after_half_history(decode_image_exr(response.content), expected[3])


def test_a_session_says_whether_redis_holds_it_and_a_failed_mirror_lands_once_redis_answers_again(api):
    import redis
    from redis.backoff import NoBackoff
    from redis.retry import Retry

    client, store = api()
    session = create(client)
    frames = stream_frames(2)
    assert post_frame(client, session["id"], frames[0]).status_code == 200
    assert store.flush(timeout=30)
    assert client.get(f"/sessions/{session['id']}").json()["mirror"] == {
        "current": True, "last_written_frame": 0, "pending_since": None}

    reachable = store.redis
    store.redis = redis.Redis(host="127.0.0.1", port=1, socket_connect_timeout=0.2, socket_timeout=0.2,
                              retry=Retry(NoBackoff(), 0))  # Redis goes away
    assert post_frame(client, session["id"], frames[1]).status_code == 200
    assert store.flush(timeout=30)
    mirror = client.get(f"/sessions/{session['id']}").json()["mirror"]  # served from memory
    assert (mirror["current"], mirror["last_written_frame"]) == (False, 0) and mirror["pending_since"]

    store.redis, store._redis_paused_until = reachable, 0.0  # back, and no longer left alone
    client.get(f"/sessions/{session['id']}")  # the first Redis call that works starts the failed write again
    assert store._writer_of(session["id"]).wait(30)  # (that write; waiting retries nothing itself)
    assert client.get(f"/sessions/{session['id']}").json()["mirror"] == {
        "current": True, "last_written_frame": 1, "pending_since": None}


def test_session_lifecycle(api):
    client, _ = api()
    first, second = create(client), create(client, on_gap="reject")
    assert first["model"]["version"] == "2"  # no version, no alias: the latest
    listed = client.get("/sessions").json()
    assert [s["id"] for s in listed] == [first["id"], second["id"]]
    assert listed[1]["on_gap"] == "reject"
    assert post_frame(client, first["id"], stream_frames(1)[0]).status_code == 200

    reset = client.post(f"/sessions/{first['id']}/reset")
    assert reset.status_code == 200
    assert reset.json()["next_frame_index"] is None and reset.json()["frames_processed"] == 1
    assert client.delete(f"/sessions/{first['id']}").status_code == 204
    for response in (client.get(f"/sessions/{first['id']}"), client.delete(f"/sessions/{first['id']}"),
                     client.post(f"/sessions/{first['id']}/reset"),
                     post_frame(client, first["id"], stream_frames(1)[0])):
        assert "does not exist" in error_message(response, 404, "not_found")
    assert [s["id"] for s in client.get("/sessions").json()] == [second["id"]]


@pytest.mark.parametrize("body, status, message", [
    ({"model": "nope"}, 404, "model 'nope' does not exist"),
    ({"model": MODEL_NAME, "version": "7"}, 404, f"version 7 of model '{MODEL_NAME}' does not exist"),
    ({"model": MODEL_NAME, "alias": "gold"}, 404, f"model '{MODEL_NAME}' has no alias 'gold'"),
    ({"model": MODEL_NAME, "version": "1", "alias": "champion"}, 422, "give a version or an alias"),
    ({"model": MODEL_NAME, "on_gap": "skip"}, 422, "on_gap"),
    ({"model": MODEL_NAME, "version": "one"}, 422, "version"),
    ({"model": MODEL_NAME, "colour": "red"}, 422, "colour"),
])
def test_bad_session_requests(api, body, status, message):
    client, _ = api()
    response = client.post("/sessions", json=body)
    assert response.status_code == status, response.text
    assert message in response.json()["error"]["message"]


def test_past_the_session_cap_is_429(api):
    client, _ = api(max_sessions=1)
    create(client)
    assert "the server's limit is 1" in error_message(client.post("/sessions", json={"model": MODEL_NAME}), 429,
                                                  "too_many_sessions")


def test_idle_sessions_expire(api):
    clock = FakeClock()
    client, _ = api(clock=clock, session_ttl_seconds=30)
    session = create(client)
    clock.advance(31)
    assert "expired or deleted" in error_message(client.get(f"/sessions/{session['id']}"), 404, "not_found")
    assert client.get("/sessions").json() == []


def test_frame_order_over_http(api):
    client, _ = api()
    frames = stream_frames(6)
    reset, reject = create(client), create(client, on_gap="reject")
    for session in (reset, reject):
        assert post_frame(client, session["id"], frames[0]).headers["x-history"] == "started"
    gap = post_frame(client, reset["id"], frames[3])
    assert gap.status_code == 200 and gap.headers["x-history"] == "reset-gap"
    message = error_message(post_frame(client, reject["id"], frames[3]), 409, "frame_gap")
    assert "expects frame_index 1" in message
    message = error_message(post_frame(client, reset["id"], frames[3]), 409, "frame_out_of_order")
    assert "frame_index 3 repeats" in message
    assert client.get(f"/sessions/{reject['id']}").json()["next_frame_index"] == 1

    larger = stream_frames(1, size=8, start=1)[0]
    message = error_message(post_frame(client, reject["id"], larger), 409, "resolution_mismatch")
    assert "8x8 but this session's frames are 16x16" in message
    client.post(f"/sessions/{reject['id']}/reset")
    response = post_frame(client, reject["id"], larger)
    assert response.headers["x-history"] == "started" and decode_image_exr(response.content).shape == (16, 16, 3)


def _raw_exr(frame, drop: str | None = None) -> bytes:
    """The frame's EXR without validation (so it can hold what read_frame refuses), minus channel ``drop``."""
    parts = _frame_parts(frame, half=False)
    if drop:
        channels = {name: channel.pixels for name, channel in parts[0].channels.items() if name != drop}
        parts[0] = OpenEXR.Part(parts[0].header, channels, "render")
    stream = io.BytesIO()
    OpenEXR.File(parts).write(stream)
    return stream.getvalue()


def test_bad_frame_bodies_are_4xx_naming_the_problem(api):
    client, _ = api(max_frame_bytes=40_000)
    session = create(client)
    frame = stream_frames(1)[0]
    valid = frame_bytes(frame)
    assert len(valid) < 40_000
    sid = session["id"]

    assert "not an OpenEXR file" in error_message(post_frame(client, sid, b"P6 16 16 255 ..."), 400, "invalid_frame")
    assert "empty" in error_message(post_frame(client, sid, b""), 400, "invalid_frame")
    assert "truncated" in error_message(post_frame(client, sid, valid[: len(valid) // 2]), 400, "invalid_frame")
    assert "buffer 'depth': required buffer is missing" in error_message(
        post_frame(client, sid, _raw_exr(frame, drop="depth.Z")), 400, "invalid_frame")
    bent = stream_frames(1)[0]
    bent.normal[2, 3] = (0.0, 0.0, 3.0)  # a convention a repair cannot guess: refused, not repaired
    response = post_frame(client, sid, _raw_exr(bent))
    assert "buffer 'normal': 1 pixels are not unit length" in error_message(response, 400, "invalid_frame")
    assert response.json()["error"]["details"]["buffer"] == "normal"

    message = error_message(post_frame(client, sid, valid, "text/plain"), 415, "unsupported_media_type")
    assert "application/octet-stream, image/x-exr" in message
    too_large = valid + bytes(40_000)
    assert "the limit is 40000 bytes" in error_message(post_frame(client, sid, too_large), 413, "payload_too_large")
    # Without a Content-Length (chunked), the body is cut off at the limit too.
    chunks = (too_large[i:i + 8192] for i in range(0, len(too_large), 8192))
    response = client.post(f"/sessions/{sid}/frames", content=chunks, headers={"Content-Type": "image/x-exr"})
    assert "at least" in error_message(response, 413, "payload_too_large")
    assert post_frame(client, "0" * 32, valid).status_code == 404
    # None of it touched the session.
    assert client.get(f"/sessions/{sid}").json()["frames_processed"] == 0
    assert post_frame(client, sid, valid).status_code == 200


def test_nan_inf_and_out_of_range_input_is_repaired_and_reported_not_propagated(api):
    client, _ = api()
    sid = create(client)["id"]
    frames = stream_frames(3)
    broken = frames[1]
    broken.color[2, 3, 1] = np.nan
    broken.color[5, 5] = np.inf
    broken.depth[7, 1] = np.inf
    broken.albedo[0, 0] = (1.5, 0.2, 0.2)
    answers = [post_frame(client, sid, _raw_exr(frame)) for frame in frames]
    assert [r.status_code for r in answers] == [200, 200, 200]
    assert [r.headers["X-Sanitized-Pixels"] for r in answers] == ["0", "4", "0"]
    assert "X-Sanitized" not in answers[0].headers
    assert answers[1].headers["X-Sanitized"] == "color: 2 non-finite; albedo: 1 out of range; depth: 1 non-finite"
    # The history carried the repaired frame: every output stays finite, the frame after included.
    assert all(np.isfinite(decode_image_exr(r.content)).all() for r in answers)
    assert answers[2].headers["X-History"] == "continued"


def test_openapi_documents_the_frame_endpoint(api):
    client, _ = api()
    operation = client.get("/openapi.json").json()["paths"]["/sessions/{session_id}/frames"]["post"]
    assert set(operation["requestBody"]["content"]) == {"application/octet-stream", "image/x-exr"}
    ok = operation["responses"]["200"]
    assert "image/x-exr" in ok["content"]
    assert {"X-History", "X-Inference-Ms", "X-Server-Ms", "X-Sanitized-Pixels", "X-Sanitized"} <= set(ok["headers"])
    assert {"400", "404", "409", "413", "415"} <= set(operation["responses"])


def test_a_decompression_bomb_frame_is_413_before_it_is_decoded(api, monkeypatch):
    import model.io.exr
    from tests.builders import zero_bomb

    client, store = api(max_frame_pixels=1_000_000)
    session = create(client)
    decoded = []
    monkeypatch.setattr(model.io.exr, "_read_coalesced", lambda *args: decoded.append(args))
    message = error_message(post_frame(client, session["id"], zero_bomb(1024, 1024)), 413, "frame_too_large")
    assert "declares 1024x1024 = 1048576 pixels; the limit is 1000000" in message
    assert decoded == []
    assert client.get(f"/sessions/{session['id']}").json()["frames_processed"] == 0


def _refuse_decodes(monkeypatch) -> None:
    import model.io.exr

    def decode(*args):
        raise AssertionError("a frame that the headers refuse was decoded")

    monkeypatch.setattr(model.io.exr, "_read_coalesced", decode)


def test_a_bomb_of_unused_channels_is_refused_from_its_header(api, monkeypatch):
    from service.http.routes import sessions as sessions_routes
    from tests.builders import aov_bomb, error_of

    # 127 unused float channels at the pixel limit: within 128 values per pixel, but 127 x 4 bytes a pixel decoded.
    bomb = aov_bomb(32, 16)
    decoded = 32 * 16 * 127 * 4
    client, _ = api(max_frame_pixels=32 * 16, max_decoded_frame_bytes=decoded - 1)
    session = create(client)
    _refuse_decodes(monkeypatch)
    trims = []
    monkeypatch.setattr(sessions_routes, "release_freed_memory", lambda: trims.append(1))
    error = error_of(post_frame(client, session["id"], bomb), 413, "frame_too_large")
    assert trims == [1]  # a refused frame gives back what it allocated
    assert f"decodes to {decoded} bytes" in error["message"] and f"the limit is {decoded - 1} bytes" in error["message"]
    assert error["details"] == {"decoded_bytes": decoded, "limit_bytes": decoded - 1}
    # Under the size limit, the missing colour is read from the header: still nothing decoded.
    client, _ = api(max_frame_pixels=32 * 16)
    session = create(client)
    message = error_message(post_frame(client, session["id"], bomb), 400, "invalid_frame")
    assert "required buffer is missing" in message and "aov000.Y" in message


def test_a_session_leaves_reference_parts_undecoded(api, monkeypatch):
    import model.io.exr as exr
    from tests.builders import with_reference_part

    # 128x128 x 3 channels x 4 bytes = 196608 bytes in reference_x8 alone: past the limit, were it decoded.
    body = frame_bytes(stream_frames(1)[0])
    client, _ = api(max_decoded_frame_bytes=64 * 1024)
    plain, with_x8 = create(client), create(client)
    opened = []
    real_read = exr._read_coalesced

    def read(target, count):
        result = real_read(target, count)
        opened.append([part.name() for part in result.parts])
        return result

    monkeypatch.setattr(exr, "_read_coalesced", read)
    response = post_frame(client, with_x8["id"], with_reference_part(body, 8))
    assert response.status_code == 200, response.text
    assert opened == [["render"]]  # reference_x2 and reference_x8 left out before decoding
    assert response.content == post_frame(client, plain["id"], body).content


@pytest.mark.slow
def test_the_full_size_unused_channel_bomb_is_refused_by_default(api, monkeypatch):
    from tests.builders import aov_bomb

    client, _ = api()
    session = create(client)
    _refuse_decodes(monkeypatch)
    message = error_message(post_frame(client, session["id"], aov_bomb(2048, 1024)), 413, "frame_too_large")
    assert "decodes to 1065353216 bytes" in message and "the limit is 536870912 bytes" in message


def test_frames_past_the_memory_budget_are_503_with_retry_after(api):
    from service.http.request_limits import frame_budget

    body = frame_bytes(stream_frames(1)[0])
    budget = 3 * len(body) // 2 + _decoded_bytes(body)  # the body and its decode fit; a second body does not
    client, _ = api(max_buffered_frame_bytes=budget)
    session = create(client)
    with frame_budget(budget).hold() as other:
        other(len(body))  # another session's frame in progress: this one would pass the budget
        response = post_frame(client, session["id"], body)
        assert response.status_code == 503 and response.headers["retry-after"] == "1"
        assert "bytes of session frames in progress" in error_message(response, 503, "server_busy")
        chunked = client.post(f"/sessions/{session['id']}/frames", content=iter([body[:100], body[100:]]),
                              headers={"Content-Type": "image/x-exr"})  # no Content-Length: held as it arrives
        error_message(chunked, 503, "server_busy")
    assert post_frame(client, session["id"], body).status_code == 200


def _decoded_bytes(body: bytes) -> int:
    from model.io.exr import decoded_part_bytes

    return sum(size for _, size in decoded_part_bytes(OpenEXR.File(io.BytesIO(body), header_only=True).parts))


def test_a_decode_past_the_memory_budget_is_503_before_decoding(api, monkeypatch):
    import model.io.exr as exr

    body = frame_bytes(stream_frames(1)[0])
    decoded = _decoded_bytes(body)
    budget = len(body) + decoded
    client, _ = api(max_buffered_frame_bytes=budget)
    session = create(client)
    decodes = []
    real_read = exr._read_coalesced
    monkeypatch.setattr(exr, "_read_coalesced", lambda *args: decodes.append(1) or real_read(*args))
    with frame_budget_hold(budget) as other:
        other(decoded // 2)  # another frame's decode in progress: this body fits the budget, its decode does not
        response = post_frame(client, session["id"], body)
        assert response.status_code == 503 and response.headers["retry-after"] == "1"
        assert "bytes of session frames in progress" in error_message(response, 503, "server_busy")
    assert decodes == []
    assert post_frame(client, session["id"], body).status_code == 200 and decodes == [1]


def frame_budget_hold(budget: int):
    from service.http.request_limits import frame_budget

    return frame_budget(budget).hold()


def test_with_owner_tokens_only_the_creator_drives_a_session(api):
    client, _ = api(session_owner_tokens=True)
    session = create(client)
    token = session["token"]
    assert token and len(token) >= 32
    mine = {"X-Session-Token": token}
    frame = frame_bytes(stream_frames(1)[0])
    for method, path, body in (("GET", "", None), ("POST", "/frames", frame), ("POST", "/reset", None),
                               ("DELETE", "", None)):
        url = f"/sessions/{session['id']}{path}"
        headers = {"Content-Type": "image/x-exr"} if body else {}
        missing = client.request(method, url, content=body, headers=headers)
        assert "X-Session-Token" in error_message(missing, 403, "session_forbidden"), (method, path)
        wrong = client.request(method, url, content=body, headers={**headers, "X-Session-Token": "x" * 32})
        error_message(wrong, 403, "session_forbidden")
    assert client.get(f"/sessions/{session['id']}", headers=mine).json()["frames_processed"] == 0
    assert post_frame_with(client, session["id"], frame, mine).status_code == 200
    assert client.get(f"/sessions/{session['id']}", headers=mine).json()["token"] is None  # only at creation
    assert client.delete(f"/sessions/{session['id']}", headers=mine).status_code == 204


def test_a_restarted_api_keeps_the_owner_token(api):
    client, store = api(session_owner_tokens=True)
    session = create(client)
    store.flush(timeout=30)
    restarted, _ = api(session_owner_tokens=True)
    error_message(restarted.get(f"/sessions/{session['id']}"), 403, "session_forbidden")
    assert restarted.get(f"/sessions/{session['id']}",
                         headers={"X-Session-Token": session["token"]}).status_code == 200


def test_with_owner_tokens_a_caller_lists_only_the_sessions_whose_tokens_it_sends(api):
    client, _ = api(session_owner_tokens=True)
    first, second, other = create(client), create(client), create(client)
    assert client.get("/sessions").json() == []  # no token: nothing, not every owner's sessions
    assert client.get("/sessions", headers={"X-Session-Token": "x" * 32}).json() == []
    listed = client.get("/sessions", headers={"X-Session-Token": first["token"]}).json()
    assert [item["id"] for item in listed] == [first["id"]]
    assert all(item["token"] is None for item in listed)
    both = {first["id"], second["id"]}
    joined = client.get("/sessions", headers={"X-Session-Token": f"{first['token']}, {second['token']}"})
    assert {item["id"] for item in joined.json()} == both
    repeated = client.get("/sessions", headers=[("X-Session-Token", first["token"]),
                                                ("X-Session-Token", second["token"])])
    assert {item["id"] for item in repeated.json()} == both
    assert other["id"] not in {item["id"] for item in repeated.json()}


def test_without_owner_tokens_every_session_is_listed(api):
    client, _ = api()
    ids = {create(client)["id"], create(client)["id"]}
    assert {item["id"] for item in client.get("/sessions").json()} == ids


def test_without_owner_tokens_sessions_have_none(api):
    client, _ = api()
    session = create(client)
    assert session["token"] is None
    assert client.get(f"/sessions/{session['id']}").status_code == 200


def post_frame_with(client, session_id, body, headers):
    return client.post(f"/sessions/{session_id}/frames", content=body,
                       headers={"Content-Type": "image/x-exr", **headers})
