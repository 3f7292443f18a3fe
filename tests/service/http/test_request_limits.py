"""Bounds on request bodies: slots taken and refused, and a body that stalls answered 408 (the BodyReadTimeout
middleware) on the real routes: archive and frame uploads and JSON bodies."""

from __future__ import annotations

import asyncio
import json

import pytest
from fastapi.testclient import TestClient

from service.http.errors import ApiError
from service.http.request_limits import BodyReadTimeout, ByteBudget, Slots, frame_budget, upload_slots
from service.http.routes import datasets, jobs
from core.settings import get_settings


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


def test_a_body_that_stalls_is_408_and_leaves_nothing(make_app, storage):
    app = make_app(datasets.router, jobs.router)
    app.add_middleware(BodyReadTimeout, timeout_seconds=0.05)  # the client never sends the rest: no race
    status, body = _call(app, "/datasets/live/sequences/cam_0/frames",
                         {"content-type": "image/x-exr", "content-length": "100"}, b"v")
    assert status == 408 and body["error"]["code"] == "body_timeout"
    assert [p.name for p in storage.staging.iterdir() if p.name != "locks"] == []
    status, body = _call(app, "/datasets", {"content-type": "application/zip", "content-length": "100"}, b"P")
    assert status == 408 and body["error"]["code"] == "body_timeout"
    status, body = _call(app, "/jobs", {"content-type": "application/json", "content-length": "100"}, b'{"kind"')
    assert status == 408 and body["error"]["code"] == "body_timeout", body


def test_the_app_bounds_body_reads_with_the_setting(settings, monkeypatch):
    from service.http.app import create_app

    monkeypatch.setenv("DENOISER_BODY_READ_TIMEOUT_SECONDS", "7.5")
    get_settings.cache_clear()
    app = create_app()
    assert [m.kwargs for m in app.user_middleware if m.cls is BodyReadTimeout] == [{"timeout_seconds": 7.5}]


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


def test_a_byte_budget_refuses_what_would_pass_it_and_frees_on_exit():
    budget = ByteBudget(100, "frames")
    with budget.hold() as first:
        first(60)
        with pytest.raises(ApiError) as info, budget.hold() as second:
            second(30)
            second(11)  # 101 held
        assert (info.value.status, info.value.code) == (503, "server_busy")
        assert budget.held == 60  # the refused holder's 30 are freed with it
    assert budget.held == 0
    assert frame_budget(100) is frame_budget(100)
