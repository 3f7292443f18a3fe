"""Bounds on request bodies: slots taken and refused, and a body that stalls answered 408, over the real routes."""

from __future__ import annotations

import asyncio
import json

import pytest
from fastapi.testclient import TestClient

from service.errors import ApiError
from service.request_limits import Slots, frame_slots, timed_chunks, upload_slots
from service.routes import datasets


def test_slots_refuse_past_their_capacity_and_free_on_exit():
    slots = Slots(1, "things", 429, "too_many_things")
    with slots.take():
        with pytest.raises(ApiError) as info, slots.take():
            pass
        assert (info.value.status, info.value.code, info.value.headers) == (429, "too_many_things",
                                                                            {"Retry-After": "1"})
        assert "1 things are in progress, the server's limit is 1" in info.value.message
    with slots.take():
        assert slots.held == 1
    assert slots.held == 0


def test_a_stalled_stream_times_out_with_408():
    async def stalls():
        yield b"x"
        await asyncio.Event().wait()  # never set: the client sends nothing more
        yield b"never"

    async def read():
        return [chunk async for chunk in timed_chunks(stalls(), 0.01)]

    with pytest.raises(ApiError) as info:
        asyncio.run(read())
    assert (info.value.status, info.value.code) == (408, "body_timeout")


def _call(app, path: str, headers: dict[str, str], first_chunk: bytes) -> tuple[int, dict]:
    """Send a request to the ASGI app whose body stops after ``first_chunk`` (the client never sends the rest)."""
    messages = [{"type": "http.request", "body": first_chunk, "more_body": True}]
    stalled = asyncio.Event()
    sent: list[dict] = []

    async def receive():
        if messages:
            return messages.pop(0)
        await stalled.wait()  # never set
        return {"type": "http.disconnect"}

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
             "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "headers": [(k.lower().encode(), v.encode()) for k, v in headers.items()], "client": ("test", 1),
             "server": ("test", 80)}
    asyncio.run(app(scope, receive, send))
    start = next(m for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return start["status"], json.loads(body)


def test_an_upload_whose_body_stalls_is_408_and_leaves_nothing(make_app, storage):
    app = make_app(datasets.router, body_read_timeout_seconds=0.05)
    status, body = _call(app, "/datasets/live/sequences/cam_0/frames",
                         {"content-type": "image/x-exr", "content-length": "100"}, b"v")
    assert status == 408 and body["error"]["code"] == "body_timeout"
    assert [p.name for p in storage.staging.iterdir() if p.name != "locks"] == []
    status, body = _call(app, "/datasets", {"content-type": "application/zip", "content-length": "100"}, b"P")
    assert status == 408 and body["error"]["code"] == "body_timeout"


def test_uploads_past_the_concurrency_limit_are_429_with_retry_after(make_app, storage):
    api = TestClient(make_app(datasets.router, max_concurrent_uploads=1))
    with upload_slots(1).take():  # another upload in progress
        response = api.post("/datasets", content=b"PK\x03\x04", headers={"Content-Type": "application/zip"})
        assert response.status_code == 429 and response.headers["retry-after"] == "1"
        assert response.json()["error"]["code"] == "too_many_uploads"
        response = api.post("/datasets/live/sequences/cam_0/frames", content=b"v",
                            headers={"Content-Type": "image/x-exr"})
        assert response.status_code == 429
    response = api.post("/datasets", content=b"PK\x03\x04", headers={"Content-Type": "application/zip"})
    assert response.status_code == 400  # taken in once the slot is free (and found not to be an archive)


def test_frame_slots_answer_503_server_busy():
    slots = frame_slots(3)
    assert slots is frame_slots(3) and (slots.status, slots.code) == (503, "server_busy")
