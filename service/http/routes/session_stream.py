"""GET /sessions/{id}/stream: a session's frames over one WebSocket, raw arrays instead of EXR files.

The same session, frame rules and model step as POST /sessions/{id}/frames (service.sessions.store.SessionStore.
process_frame, the frame read as the ``denoiser`` layout reads it in live mode: service.sessions.stream_batch, which gives
what model.layouts.read_bundle_buffers does, from the message's planes, as torch tensors), without the per-frame
HTTP request and the EXR encode and decode on either side. Messages are packed by
client.codec (the protocol: docs/service.md, "Streaming over a WebSocket").

One connection drives one session; its binary messages are frames, answered in order, one output message each. A
frame the session refuses (bad input, frame order, a busy server) is answered with a JSON text message in the API's
error shape, plus the REST API's status for the same error and the frame's index when it could be read:
``{"error": {"code", "message", "details"}, "status": 409, "frame_index": 7}``; the socket stays open and the
session keeps its history, as after a refused POST. What ends the connection is closed with an application close
code of 4000 + the HTTP status the REST API gives the same error (CLOSE_CODES), the reason naming it ("code:
message", cut to 123 bytes): no or a wrong API key 4401, not the session's owner 4403, no such session (never
created, deleted or expired, also mid-stream) 4404, the session store unreachable when connecting 4503; an
unexpected server error 1011. A message larger than the server's WebSocket limit (uvicorn's ``--ws-max-size``,
which ``denoiser serve`` sets to DENOISER_MAX_FRAME_BYTES) is closed with 1009 by the server.

Authentication is the REST API's, checked here rather than by the router's dependency (a WebSocket has no HTTP
error response to give): X-API-Key and X-Session-Token headers on the upgrade request.
"""

from __future__ import annotations

import json
import logging
import time
from typing import Annotated

from fastapi import APIRouter, Depends, WebSocket, WebSocketDisconnect
from starlette.concurrency import run_in_threadpool

from model.io.frames import FrameError
from service.http.auth import API_KEY_HEADER, require_api_key
from service.http.errors import ApiError, api_error, domain_errors, frame_error_details
from service.http.request_limits import frame_budget
from service.http.routes.sessions import SESSION_TOKEN_HEADER, check_owner
from service.sessions.store import ReadFrame, SessionStore, get_session_store
from core.settings import Settings, get_settings
from service.sessions.stream_batch import stream_frame_batch
from client.codec import StreamMessageError, decode_frame, encode_output

log = logging.getLogger("denoiser.sessions")

router = APIRouter(prefix="/sessions", tags=["sessions"])

StoreDep = Annotated[SessionStore, Depends(get_session_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]

STREAM_SOURCE = "frame message"  # how frame errors name a message
CLOSE_INTERNAL_ERROR = 1011
# The close code of an error that ends the stream: 4000 + the REST API's status for it.
CLOSE_CODES = {401: 4401, 403: 4403, 404: 4404, 503: 4503}
_REASON_BYTES = 123  # a close frame's reason is at most 123 bytes


def _reason(error: ApiError) -> str:
    text = f"{error.code}: {error.message}".encode()
    return text[:_REASON_BYTES].decode(errors="ignore")


@router.websocket("/{session_id}/stream")
async def stream_session(websocket: WebSocket, session_id: str, store: StoreDep, settings: SettingsDep) -> None:
    await websocket.accept()
    try:
        await run_in_threadpool(_admit, store, settings, session_id, websocket.headers.get(API_KEY_HEADER),
                                websocket.headers.get(SESSION_TOKEN_HEADER))
    except ApiError as error:
        await websocket.close(CLOSE_CODES.get(error.status, CLOSE_INTERNAL_ERROR), _reason(error))
        return
    try:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            data = message.get("bytes")
            if data is None:
                await _send_error(websocket, ApiError(400, "invalid_message", "frames are binary messages; this "
                                                                              "one was text"), None)
                continue
            try:
                answer = await _frame(store, settings, session_id, data)
            except _FrameFailed as failed:
                if failed.error.status == 404:  # deleted or expired meanwhile: nothing more can be streamed
                    await websocket.close(CLOSE_CODES[404], _reason(failed.error))
                    return
                await _send_error(websocket, failed.error, failed.frame_index)
                continue
            try:
                await websocket.send_bytes(answer)
            finally:
                store.start_mirror(session_id)  # as POST does once the response is out (never blocks)
    except WebSocketDisconnect:
        return
    except Exception:
        log.exception("session %s: stream failed", session_id)
        await websocket.close(CLOSE_INTERNAL_ERROR, "internal_error: the server failed on this frame")


class _FrameFailed(Exception):
    """A frame that got no output: the API error to answer, and the frame's index when it could be read."""

    def __init__(self, error: ApiError, frame_index: int | None = None) -> None:
        super().__init__(error.message)
        self.error = error
        self.frame_index = frame_index


def _admit(store: SessionStore, settings: Settings, session_id: str, key: str | None, token: str | None) -> None:
    """The REST API's checks: the API key, the session's existence, its owner token (ApiError otherwise)."""
    require_api_key(settings, key)
    with domain_errors():
        store.get(session_id)
    check_owner(store, session_id, token)


async def _frame(store: SessionStore, settings: Settings, session_id: str, data: bytes) -> bytes:
    """One frame message -> its output message; _FrameFailed otherwise."""
    started = time.perf_counter()
    if len(data) > settings.max_frame_bytes:
        raise _FrameFailed(ApiError(413, "payload_too_large", f"the frame message is {len(data)} bytes; the limit "
                                                              f"is {settings.max_frame_bytes} bytes",
                                    {"limit_bytes": settings.max_frame_bytes}))
    try:
        # The message's bytes count against the frame memory budget until its output is packed, as POST bodies do.
        with frame_budget(settings.max_buffered_frame_bytes).hold() as hold:
            hold(len(data))
            return await run_in_threadpool(_run_frame, store, session_id, data, settings.max_frame_pixels, started)
    except ApiError as error:  # server_busy
        raise _FrameFailed(error) from None


def _run_frame(store: SessionStore, session_id: str, data: bytes, max_pixels: int, started: float) -> bytes:
    """The output message of a frame message, on a worker thread: unpack, read as POST reads a frame (on one of
    the store's frame-reading threads), step; _FrameFailed otherwise."""
    try:
        message = decode_frame(data, max_pixels=max_pixels)
    except StreamMessageError as error:
        raise _FrameFailed(api_error(error)) from None
    index = message.frame_index
    try:
        read = store.read_frame(lambda device: stream_frame_batch(message, device, STREAM_SOURCE))
    except FrameError as error:
        raise _FrameFailed(api_error(error, frame_error_details(error)), index) from None
    frame = ReadFrame(index or 0, message.width, message.height, message.camera_cut, read.batch,
                      plainly_valid=read.plainly_valid, output_dtype=message.output_dtype)
    try:
        with domain_errors():
            result = store.process_frame(session_id, frame, start_mirror=False, frame_index_given=index is not None)
    except ApiError as error:
        raise _FrameFailed(error, index) from None
    try:
        header = {"frame_index": result.frame_index, "history": result.history,
                  "inference_ms": round(result.inference_ms, 3), "sanitized_pixels": result.sanitized.total}
        if not result.sanitized.clean:
            header["sanitized"] = result.sanitized.describe()
        if read.repairs:
            header["repairs"] = "; ".join(read.repairs)
        header["server_ms"] = round((time.perf_counter() - started) * 1000, 3)
        return encode_output(result.output, dtype=message.output_dtype, **header)
    except BaseException:
        store.start_mirror(session_id)  # no output will start it
        raise


async def _send_error(websocket: WebSocket, error: ApiError, frame_index: int | None) -> None:
    await websocket.send_text(json.dumps({"error": {"code": error.code, "message": error.message,
                                                    "details": error.details},
                                          "status": error.status, "frame_index": frame_index}))
