"""GET /sessions/{id}/stream: a session's frames over one WebSocket, raw arrays instead of EXR files.

The same session, frame rules and model step as POST /sessions/{id}/frames (service.sessions.store.SessionStore.
process_frame, the frame read as the ``denoiser`` layout reads it in live mode: service.sessions.stream_batch, which gives
what model.layouts.read_bundle_buffers does, from the message's planes, as torch tensors), without the per-frame
HTTP request and the EXR encode and decode on either side. Messages are packed by
client.codec (the protocol: docs/service.md, "Streaming over a WebSocket").

One connection drives one session; its binary messages are frames, answered in order, one output message each, one
step at a time; the next message is read while a frame steps, so a client may send ahead (_serve). A
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

import asyncio
import json
import logging
import time
from contextlib import ExitStack
from typing import Annotated, NamedTuple

from fastapi import APIRouter, Depends, WebSocket, WebSocketDisconnect
from starlette.concurrency import run_in_threadpool

from model.io.frames import FrameError
from service.http.auth import API_KEY_HEADER, require_api_key
from service.http.errors import ApiError, api_error, domain_errors, frame_error_details
from service.http.request_limits import frame_budget
from service.http.routes.sessions import SESSION_TOKEN_HEADER, check_owner
from service.sessions.store import ReadFrame, SessionStore, get_session_store
from core.settings import Settings, get_settings
from service.sessions.stream_batch import StreamRead, stream_frame_batch
from client.codec import StreamFrame, StreamMessageError, decode_frame, encode_output

log = logging.getLogger("denoiser.sessions")

router = APIRouter(prefix="/sessions", tags=["sessions"])

StoreDep = Annotated[SessionStore, Depends(get_session_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]

STREAM_SOURCE = "frame message"  # how frame errors name a message
CLOSE_INTERNAL_ERROR = 1011
# The close code of an error that ends the stream: 4000 + the REST API's status for it.
CLOSE_CODES = {401: 4401, 403: 4403, 404: 4404, 503: 4503}
_REASON_BYTES = 123  # a close frame's reason is at most 123 bytes
READ_AHEAD = 1  # frames of a stream read while the frame before them steps: the next one is all a step can use


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
        await _serve(websocket, store, settings, session_id)
    except WebSocketDisconnect:
        return
    except Exception:
        log.exception("session %s: stream failed", session_id)
        await websocket.close(CLOSE_INTERNAL_ERROR, "internal_error: the server failed on this frame")


async def _serve(websocket: WebSocket, store: SessionStore, settings: Settings, session_id: str) -> None:
    """Answer the stream's frames in order, one step at a time. A receiver takes the next message off the socket
    and reads it into tensors (on the store's frame-reading threads) while the frame before it steps, so a client
    that sends ahead (SessionStream.send_many) has the next frame ready when the step ends; at most READ_AHEAD
    frames wait read."""
    slots = asyncio.Semaphore(READ_AHEAD + 1)  # frames received and not answered yet
    reads: asyncio.Queue = asyncio.Queue()
    receiver = asyncio.create_task(_receive(websocket, store, settings, slots, reads))
    try:
        while True:
            item = await reads.get()
            if item is None:  # the client went away
                return
            if isinstance(item, BaseException):
                raise item
            try:
                answer = await _answer(store, session_id, item)
            except _FrameFailed as failed:
                if failed.error.status == 404:  # deleted or expired meanwhile: nothing more can be streamed
                    await websocket.close(CLOSE_CODES[404], _reason(failed.error))
                    return
                await _send_error(websocket, failed.error, failed.frame_index)
                continue
            finally:
                slots.release()
            try:
                await websocket.send_bytes(answer)
            finally:
                store.start_mirror(session_id)  # as POST does once the response is out (never blocks)
    finally:
        receiver.cancel()
        while not reads.empty():  # frames read ahead and never answered: free their share of the frame budget
            item = reads.get_nowait()
            if isinstance(item, asyncio.Future):
                item.add_done_callback(_release_unanswered)


async def _receive(websocket: WebSocket, store: SessionStore, settings: Settings, slots: asyncio.Semaphore,
                   reads: asyncio.Queue) -> None:
    """Put each message's read (a task giving a _Read, or raising _FrameFailed) on ``reads`` in arrival order;
    None once the client disconnects, or the exception that stopped the receiving."""
    try:
        while True:
            await slots.acquire()
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                reads.put_nowait(None)
                return
            reads.put_nowait(asyncio.ensure_future(_read(store, settings, message.get("bytes"))))
    except asyncio.CancelledError:
        raise
    except Exception as error:  # the handler raises it, in order
        reads.put_nowait(error)


class _FrameFailed(Exception):
    """A frame that got no output: the API error to answer, and the frame's index when it could be read."""

    def __init__(self, error: ApiError, frame_index: int | None = None) -> None:
        super().__init__(error.message)
        self.error = error
        self.frame_index = frame_index


class _Read(NamedTuple):
    """A frame message read into its batch, holding its bytes' share of the frame budget until ``budget`` closes."""

    message: StreamFrame
    read: StreamRead
    budget: ExitStack
    started: float


def _admit(store: SessionStore, settings: Settings, session_id: str, key: str | None, token: str | None) -> None:
    """The REST API's checks: the API key, the session's existence, its owner token (ApiError otherwise)."""
    require_api_key(settings, key)
    with domain_errors():
        store.get(session_id)
    check_owner(store, session_id, token)


async def _read(store: SessionStore, settings: Settings, data: bytes | None) -> _Read:
    """One message read, before its session is touched; _FrameFailed if it cannot be."""
    started = time.perf_counter()
    if data is None:
        raise _FrameFailed(ApiError(400, "invalid_message", "frames are binary messages; this one was text"))
    if len(data) > settings.max_frame_bytes:
        raise _FrameFailed(ApiError(413, "payload_too_large", f"the frame message is {len(data)} bytes; the limit "
                                                              f"is {settings.max_frame_bytes} bytes",
                                    {"limit_bytes": settings.max_frame_bytes}))
    budget = ExitStack()
    try:
        # The message's bytes count against the frame memory budget until its output is packed, as POST bodies do.
        budget.enter_context(frame_budget(settings.max_buffered_frame_bytes).hold())(len(data))
        message, read = await run_in_threadpool(_read_frame, store, data, settings.max_frame_pixels)
    except ApiError as error:  # server_busy
        budget.close()
        raise _FrameFailed(error) from None
    except BaseException:
        budget.close()
        raise
    return _Read(message, read, budget, started)


def _read_frame(store: SessionStore, data: bytes, max_pixels: int) -> tuple[StreamFrame, StreamRead]:
    """Unpack a frame message and read it as POST reads a frame (on one of the store's frame-reading threads)."""
    try:
        message = decode_frame(data, max_pixels=max_pixels)
    except StreamMessageError as error:
        raise _FrameFailed(api_error(error)) from None
    try:
        return message, store.read_frame(lambda device: stream_frame_batch(message, device, STREAM_SOURCE))
    except FrameError as error:
        raise _FrameFailed(api_error(error, frame_error_details(error)), message.frame_index) from None


async def _answer(store: SessionStore, session_id: str, reading: asyncio.Future) -> bytes:
    """The output message of a frame once it is read; _FrameFailed otherwise."""
    read = await reading
    try:
        return await run_in_threadpool(_step_frame, store, session_id, read)
    finally:
        read.budget.close()


def _step_frame(store: SessionStore, session_id: str, read: _Read) -> bytes:
    """Step a read frame in its session, on a worker thread, and pack its output message."""
    message, index = read.message, read.message.frame_index
    frame = ReadFrame(index or 0, message.width, message.height, message.camera_cut, read.read.batch,
                      plainly_valid=read.read.plainly_valid, output_dtype=message.output_dtype)
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
        if read.read.repairs:
            header["repairs"] = "; ".join(read.read.repairs)
        header["server_ms"] = round((time.perf_counter() - read.started) * 1000, 3)
        return encode_output(result.output, dtype=message.output_dtype, **header)
    except BaseException:
        store.start_mirror(session_id)  # no output will start it
        raise


def _release_unanswered(reading: asyncio.Future) -> None:
    if not reading.cancelled() and reading.exception() is None:
        reading.result().budget.close()


async def _send_error(websocket: WebSocket, error: ApiError, frame_index: int | None) -> None:
    await websocket.send_text(json.dumps({"error": {"code": error.code, "message": error.message,
                                                    "details": error.details},
                                          "status": error.status, "frame_index": frame_index}))
