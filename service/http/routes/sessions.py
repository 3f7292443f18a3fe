"""/sessions: stream frame bundles through a registered model; the server keeps each stream's history.

HTTP only: service.sessions.store.SessionStore holds the sessions (memory + Redis mirror) and runs the frames. Here:
the request body is read with the frame size limit, parsed as a frame bundle EXR, and the output is answered as a
one-part float32 RGB EXR with timing headers. Parsing, inference and encoding run in the thread pool so the event
loop keeps serving other sessions meanwhile; the frame's Redis mirror is started once the response is sent (see
service.sessions.store).
"""

from __future__ import annotations

import hmac
import secrets
import time
from collections.abc import Callable
from datetime import datetime, timezone
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Request, Response
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool

from model.deployment.malloc import release_freed_memory
from model.io.exr import encode_image_exr
from model.io.frames import FrameError
from model.layouts import LayoutFrame, layout_from_value, read_layout_frame_bytes
from model.methods.registry import method_buffers
from service.http.errors import ApiError, api_error, documented_error, domain_errors, frame_error_details
from service.http.identifiers import SessionId
from core.names import AUTO_MODEL
from service.http.request_limits import frame_budget
from service.http.schemas.sessions import SessionIn, SessionMirrorOut, SessionModelOut, SessionOut
from service.sessions.store import Session, SessionStore, get_session_store, token_digest
from core.settings import Settings, get_settings

router = APIRouter(prefix="/sessions", tags=["sessions"])

StoreDep = Annotated[SessionStore, Depends(get_session_store)]
SettingsDep = Annotated[Settings, Depends(get_settings)]
SESSION_TOKEN_HEADER = "X-Session-Token"
SessionToken = Annotated[str | None, Header(alias=SESSION_TOKEN_HEADER, description="the session's owner token "
                                            "(the `token` of its creation), where the server has owner tokens on")]

FRAME_TYPES = ("application/octet-stream", "image/x-exr")
EXR_MEDIA_TYPE = "image/x-exr"
FRAME_SOURCE = "frame body"  # how frame errors name the request body


_NOT_FOUND = documented_error("no such session (never created, deleted, or expired)", "not_found",
                              "session '0f8fad5bd9cb469fa16570867728950e' does not exist (expired or deleted)")
_FORBIDDEN = documented_error("the server has owner tokens on and X-Session-Token is missing or not this "
                               "session's token", "session_forbidden", "session '0f8f...' belongs to the client that "
                                                                       "created it: send its token in X-Session-Token")
_UNAVAILABLE = documented_error("Redis (the session store) or the model registry cannot be reached",
                                "session_store_unavailable", "session '0f8f...' is not in memory and the session "
                                                             "store (Redis) is unreachable: Connection refused")


def check_owner(store: SessionStore, session_id: str, token: str | None) -> None:
    """403 unless ``token`` is the session's owner token (sessions created without one answer any key holder)."""
    with domain_errors():
        digest = store.owner_digest(session_id)
    if digest is None:
        return
    if token is None:
        raise ApiError(403, "session_forbidden", f"session {session_id!r} belongs to the client that created it: "
                                                 f"send its token in {SESSION_TOKEN_HEADER}")
    if not hmac.compare_digest(token_digest(token), digest):
        raise ApiError(403, "session_forbidden", f"the {SESSION_TOKEN_HEADER} header is not session "
                                                 f"{session_id!r}'s token")


def _time(seconds: float) -> datetime:
    return datetime.fromtimestamp(seconds, tz=timezone.utc)


def session_out(session: Session) -> SessionOut:
    model = dict(session.model.__dict__)
    choice = model.pop("choice", None)
    return SessionOut(id=session.id, model=SessionModelOut(**model, buffers=list(method_buffers(model["method"]))),
                      choice=choice,
                      created_at=_time(session.created_at), last_used_at=_time(session.last_used_at),
                      expires_at=_time(session.expires_at), frames_processed=session.frames_processed,
                      next_frame_index=session.next_frame_index, on_gap=session.on_gap,
                      resolution=list(session.resolution) if session.resolution else None, layout=session.layout,
                      mirror=_mirror_out(session))


def _mirror_out(session: Session) -> SessionMirrorOut:
    state = session.mirror_state()
    return SessionMirrorOut(current=state.current, last_written_frame=state.last_written_frame,
                            pending_since=None if state.pending_since is None else _time(state.pending_since))


def _session_link(path: str, method: str) -> dict:
    pointer = path.replace("~", "~0").replace("/", "~1")
    return {"operationRef": f"#/paths/{pointer}/{method}", "parameters": {"session_id": "$response.body#/id"}}


# OpenAPI links: where the id of a created session goes (clients and stateful API testers follow them).
_SESSION_LINKS = {"GetSession": _session_link("/sessions/{session_id}", "get"),
                  "PostFrame": _session_link("/sessions/{session_id}/frames", "post"),
                  "ResetSession": _session_link("/sessions/{session_id}/reset", "post"),
                  "DeleteSession": _session_link("/sessions/{session_id}", "delete")}


@router.post("", status_code=201, response_model=SessionOut,
             summary="Open a session on a registered model, a pretrained model or a method",
             responses={201: {"description": "the session; its URL is in the Location header",
                              "links": _SESSION_LINKS},
                        400: documented_error("the body is not JSON", "invalid_json",
                                              "the body is not valid JSON at character 10"),
                        415: documented_error("the body was not sent as application/json", "unsupported_media_type",
                                              "Content-Type text/plain is not accepted here; send the body as "
                                              "JSON with Content-Type application/json"),
                        404: documented_error("unknown model, version or alias; an unknown name lists the registered "
                                              "models, pretrained models and methods in details (model 'auto': no "
                                              "version has the tags to compare, code no_candidate_model)",
                                              "not_found", "model 'jnds-xs-x2' has no alias 'champion' (aliases: "
                                                           "none)"),
                        422: documented_error("malformed request or model name (invalid_model_name), a learned "
                                              "method by name (untrained_method), an unknown preset, a scale the "
                                              "model cannot run at, or the model cannot be loaded (model 'auto': no "
                                              "version meets the constraint, code constraint_not_met)",
                                              "invalid_request", "give a version or an alias of model "
                                                                 "'jnds-xs-x2', not both"),
                        429: documented_error("the server's session limit is reached", "too_many_sessions",
                                              "16 sessions are open, the server's limit is 16: delete a session "
                                              "or wait for an idle one to expire (1800 s)"),
                        503: _UNAVAILABLE})
def create_session(body: SessionIn, response: Response, store: StoreDep, settings: SettingsDep) -> SessionOut:
    """`model` is a registered model (its `version`, else the version `alias` points at now, else its latest
    version), a pretrained model shipped with the service (`denoiser pretrained`), or a method without weights by
    the names `denoiser evaluate` takes (`oidn:high`, `oidn-taa`, `svgf`, `accumulation`; `scale` 1 or 2, default
    1). A name with ':' is a method; a bare name is looked up in that order. It is loaded (shared with other
    sessions of the same model) before the session is answered. An unknown name is 404 listing what exists; a
    malformed one 422 `invalid_model_name`; a learned method by name 422 `untrained_method`.

    `"model": "auto"` chooses among registered versions by their tags (docs/service.md): with `min_psnr`
    the smallest (FLOPs per pixel) whose validation PSNR is at least that, with `max_ms_per_frame` alone the best
    validation PSNR among those whose recorded ms per frame is within it, with both the smallest that meets both;
    `family` and `scale` narrow the candidates. The response's `choice` names the version and why. 404
    `no_candidate_model` when no version has the tags to compare, 422 `constraint_not_met` when none passes."""
    choice = None
    if body.model == AUTO_MODEL:
        choice = _choose(store, body)
    token = secrets.token_urlsafe(24) if settings.session_owner_tokens else None
    owner = token_digest(token) if token is not None else None
    with domain_errors():
        if choice is None:
            session = store.create(body.model, version=body.version, alias=body.alias, on_gap=body.on_gap,
                                   owner_digest=owner, layout=body.layout, scale=body.scale)
        else:
            session = store.create(choice.info.name, version=choice.info.version, on_gap=body.on_gap,
                                   choice=choice.to_dict(), owner_digest=owner, layout=body.layout)
    response.headers["Location"] = f"/sessions/{session.id}"
    out = session_out(session)
    out.token = token
    return out


def _choose(store: SessionStore, body: SessionIn):
    """The version a model 'auto' session runs (core.registry.choose_auto), or the API error saying why none."""
    from core.registry import choose_auto

    with domain_errors():
        return choose_auto(max_ms_per_frame=body.max_ms_per_frame, min_psnr=body.min_psnr, family=body.family,
                           scale=body.scale, registry=store.registry)


# Listing with owner tokens on: the caller's tokens, as a repeated header or comma-separated in one (the same to
# HTTP; tokens are URL-safe base64, so they never hold a comma).
OwnerTokens = Annotated[list[str] | None, Header(
    alias=SESSION_TOKEN_HEADER, description="where the server has owner tokens on: the caller's session tokens "
                                            "(repeat the header, or separate them with commas); only those "
                                            "sessions are listed")]


def owned_digests(tokens: list[str] | None) -> set[str]:
    return {token_digest(token.strip()) for value in tokens or () for token in value.split(",") if token.strip()}


@router.get("", response_model=list[SessionOut], summary="List live sessions", responses={503: _UNAVAILABLE})
def list_sessions(store: StoreDep, settings: SettingsDep, tokens: OwnerTokens = None) -> list[SessionOut]:
    """Every live session; with owner tokens on (DENOISER_SESSION_OWNER_TOKENS), only those whose token the
    caller sends in X-Session-Token (repeated, or comma-separated): none without one."""
    with domain_errors():
        sessions = store.list()
    if settings.session_owner_tokens:
        # A session without an owner (created before owner tokens were on) belongs to no caller: not listed.
        mine = owned_digests(tokens)
        sessions = [session for session in sessions if session.owner_digest in mine]
    return [session_out(session) for session in sessions]


@router.get("/{session_id}", response_model=SessionOut, summary="A session's model and stream position",
            responses={403: _FORBIDDEN, 404: _NOT_FOUND, 503: _UNAVAILABLE})
def get_session(session_id: SessionId, store: StoreDep, token: SessionToken = None) -> SessionOut:
    check_owner(store, session_id, token)
    with domain_errors():
        return session_out(store.get(session_id))


@router.post("/{session_id}/reset", response_model=SessionOut, summary="Drop a session's history",
             responses={403: _FORBIDDEN, 404: _NOT_FOUND, 503: _UNAVAILABLE})
def reset_session(session_id: SessionId, store: StoreDep, token: SessionToken = None) -> SessionOut:
    """The next frame starts a new history at any frame_index and may have a new resolution."""
    check_owner(store, session_id, token)
    with domain_errors():
        return session_out(store.reset(session_id))


@router.delete("/{session_id}", status_code=204, summary="Close a session",
               responses={403: _FORBIDDEN, 404: _NOT_FOUND, 503: _UNAVAILABLE})
def delete_session(session_id: SessionId, store: StoreDep, token: SessionToken = None) -> Response:
    check_owner(store, session_id, token)
    with domain_errors():
        store.delete(session_id)
    release_freed_memory()  # the session's history and step buffers, which the tuned heap would otherwise keep
    return Response(status_code=204)


_FRAME_HEADERS = {
    "X-Frame-Index": {"description": "frame_index of the frame this output is for", "schema": {"type": "integer"}},
    "X-History": {"description": "what happened to the history: started, continued, reset-gap (frames were "
                                 "skipped, on_gap=reset) or reset-camera-cut (the frame has camera_cut set)",
                  "schema": {"type": "string", "enum": ["started", "continued", "reset-gap", "reset-camera-cut"]}},
    "X-Inference-Ms": {"description": "milliseconds in method.step", "schema": {"type": "number"}},
    "X-Server-Ms": {"description": "milliseconds of the whole request in the server (body read, EXR decode, "
                                   "inference, EXR encode)", "schema": {"type": "number"}},
    "X-Sanitized-Pixels": {"description": "input pixels repaired before the step (NaN / Inf, negative radiance, "
                                          "out-of-range guides; model.io.sanitize); 0 for a clean frame",
                           "schema": {"type": "integer"}},
    "X-Sanitized": {"description": "only when X-Sanitized-Pixels > 0: what was repaired, per buffer, e.g. "
                                   "'color: 12 non-finite; depth: 3 out of range'", "schema": {"type": "string"}},
    "X-Ignored-Channels": {"description": "only when the frame had some: channels the session's layout does not use "
                                          "(ignored)", "schema": {"type": "string"}},
    "X-Repairs": {"description": "only when there were some: what reading the frame in the session's layout "
                                 "repaired, e.g. 'normal: 12 pixels renormalised (worst |n| = 0.97; lossy "
                                 "compression?)' or a missing jitter read as 0", "schema": {"type": "string"}},
}


@router.post(
    "/{session_id}/frames",
    response_class=Response,
    summary="Denoise (and upscale) the next frame of the stream",
    responses={
        200: {"description": "the output: one-part EXR, float32 R, G, B at scale x render resolution",
              "content": {EXR_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
              "headers": _FRAME_HEADERS},
        400: documented_error("the body is not a valid frame bundle EXR (the message names the buffer and problem)",
                              "invalid_frame", "frame body: buffer 'color': 3 values are negative (radiance must be "
                                               ">= 0)"),
        403: _FORBIDDEN,
        404: _NOT_FOUND,
        409: documented_error("frame_index or resolution does not continue the session (codes frame_gap, "
                              "frame_out_of_order, resolution_mismatch)", "frame_out_of_order",
                              "frame_index 4 repeats the last frame processed (4); this session expects "
                              "frame_index 5 (reset the session to restart the stream)"),
        413: documented_error("the body is larger than the server's frame limit (payload_too_large), or its "
                              "headers declare more pixels than the pixel limit, or a decode (all parts and "
                              "channels) larger than DENOISER_MAX_DECODED_FRAME_BYTES (frame_too_large), refused "
                              "before decoding",
                              "frame_too_large", "frame body: declares 2048x2048 = 4194304 pixels; the limit is "
                                                 "2097152 pixels per frame"),
        408: documented_error("the client paused longer than the body read timeout while sending the frame",
                              "body_timeout", "the request body stalled: nothing arrived for 30 s; send the whole "
                                              "body without pausing"),
        415: documented_error("Content-Type not accepted", "unsupported_media_type",
                              "Content-Type text/plain is not accepted here; send application/octet-stream, "
                              "image/x-exr"),
        503: documented_error("the session store or the registry cannot be reached (session_store_unavailable), "
                              "or the frames in progress hold the server's frame memory budget (server_busy, "
                              "Retry-After)", "server_busy", "the server holds 1073000000 bytes of session frames in "
                                                            "progress, its limit is 1073741824: retry in a moment"),
    },
    openapi_extra={"requestBody": {
        "required": True,
        "description": "one frame bundle EXR, as model.io.exr.write_frame writes it (references optional; "
                       "reference parts are not decoded)",
        "content": {kind: {"schema": {"type": "string", "format": "binary"}} for kind in FRAME_TYPES}}},
)
async def post_frame(session_id: SessionId, request: Request, store: StoreDep, settings: SettingsDep,
                     token: SessionToken = None) -> Response:
    """Frame order: the first frame (or the first after a reset) starts the history at any frame_index; then
    frame_index == next continues it; a larger one skips frames (history reset, X-History: reset-gap, or 409
    frame_gap when the session has on_gap=reject); a smaller one (a repeat or backwards) is 409
    frame_out_of_order. Every frame must have the resolution of the first one since the last reset (409
    resolution_mismatch)."""
    started = time.perf_counter()
    _check_content_type(request)
    if not store.exists(session_id):  # one in memory is checked against Redis when its frame runs
        with domain_errors():
            await run_in_threadpool(store.get, session_id)  # 404 before receiving a body for nothing
    await run_in_threadpool(check_owner, store, session_id, token)
    # The body's bytes count against the frame budget from the first byte until the output is encoded: bounds
    # the memory all frames in progress hold, whatever their number.
    with frame_budget(settings.max_buffered_frame_bytes).hold() as hold:
        body = await _read_body(request, settings.max_frame_bytes, hold)
        with domain_errors():
            result, data, read = await run_in_threadpool(_run_frame, store, session_id, body,
                                                         settings.max_frame_pixels, settings.max_decoded_frame_bytes,
                                                         hold)
    headers = {"X-Frame-Index": str(result.frame_index), "X-History": result.history,
               "X-Inference-Ms": f"{result.inference_ms:.3f}", "X-Sanitized-Pixels": str(result.sanitized.total),
               "X-Server-Ms": f"{(time.perf_counter() - started) * 1000:.3f}"}
    if not result.sanitized.clean:
        headers["X-Sanitized"] = result.sanitized.describe()
    headers.update(layout_headers(read))
    # The session's Redis mirror is written once the response is out (see service.sessions.store: at most the frame
    # in flight is missing from Redis, and the session's next request waits for the write).
    return Response(content=data, media_type=EXR_MEDIA_TYPE, headers=headers,
                    background=BackgroundTask(_start_mirror, store, session_id))


def _run_frame(store: SessionStore, session_id: str, body: bytes, max_pixels: int, max_decoded_bytes: int,
               reserve: Callable[[int], None]):
    try:
        read = _parse_frame(body, store.layout(session_id), max_pixels, max_decoded_bytes, reserve)
    except BaseException:
        release_freed_memory()  # what a refused or failed decode allocated, which the heap would otherwise keep
        raise
    frame = read.frame
    result = store.process_frame(session_id, frame, start_mirror=False, frame_index_given=read.frame_index_given)
    try:
        data = encode_image_exr(result.output, {"frame_index": result.frame_index, "sequence": frame.sequence,
                                                "scale": result.session.model.scale})
    except BaseException:
        store.start_mirror(session_id)  # no response will start it
        raise
    return result, data, read


def layout_headers(read: LayoutFrame) -> dict[str, str]:
    """X-Ignored-Channels (channels the layout does not use) and X-Repairs (renormalised normals, a missing jitter),
    each only when there is something to say; non-ASCII channel names escaped (headers are Latin-1)."""
    headers = {}
    if read.ignored_channels:
        headers["X-Ignored-Channels"] = ", ".join(read.ignored_channels)
    if read.repairs:
        headers["X-Repairs"] = "; ".join(read.repairs)
    return {key: value.encode("ascii", "backslashreplace").decode() for key, value in headers.items()}


async def _start_mirror(store: SessionStore, session_id: str) -> None:
    store.start_mirror(session_id)  # never blocks: hands the write to the store's writer threads


def _parse_frame(body: bytes, layout: str | dict, max_pixels: int, max_decoded_bytes: int | None = None,
                 reserve: Callable[[int], None] | None = None) -> LayoutFrame:
    try:
        # NaN / Inf / out-of-range values pass here and are repaired before the step (X-Sanitized-Pixels); "live"
        # also renormalises lossy-compressed normals and reads a missing jitter as 0 (X-Repairs). The header's
        # pixel count and decoded size are checked (413) and the decode's bytes reserved in the frame budget (503)
        # before anything is decoded, whatever the layout. A session never reads references: their parts are left
        # out undecoded.
        return read_layout_frame_bytes(body, layout_from_value(layout), FRAME_SOURCE, mode="live",
                                       max_pixels=max_pixels, max_decoded_bytes=max_decoded_bytes, reserve=reserve,
                                       read_references=False)
    except FrameError as error:
        raise api_error(error, frame_error_details(error)) from None


def _check_content_type(request: Request) -> None:
    declared = request.headers.get("content-type")
    if declared is None:
        return  # raw bytes without a type: read as a frame like application/octet-stream
    media_type = declared.split(";", 1)[0].strip().lower()
    if media_type not in FRAME_TYPES:
        raise ApiError(415, "unsupported_media_type", f"Content-Type {media_type} is not accepted here; send "
                                                      f"{', '.join(FRAME_TYPES)}", {"accepted": list(FRAME_TYPES)})


async def _read_body(request: Request, limit: int, hold: Callable[[int], None]) -> bytes:
    """The whole body, refusing (413) past ``limit`` bytes without reading further; its bytes are ``hold``-ed (a
    declared length at once, so a frame the budget cannot take is refused before it is read)."""
    declared = request.headers.get("content-length", "")
    if declared.isdigit() and int(declared) > limit:
        raise _too_large(int(declared), limit)
    reserved = int(declared) if declared.isdigit() else 0
    hold(reserved)
    chunks, size = [], 0
    async for chunk in request.stream():  # each read bounded by the BodyReadTimeout middleware (408)
        size += len(chunk)
        if size > limit:
            raise _too_large(size, limit, at_least=True)
        if size > reserved:  # no (or a wrong) Content-Length: held as it arrives
            hold(size - reserved)
            reserved = size
        chunks.append(chunk)
    if size == 0:
        raise ApiError(400, "invalid_frame", f"{FRAME_SOURCE}: empty; send one frame bundle EXR")
    return b"".join(chunks)


def _too_large(size: int, limit: int, at_least: bool = False) -> ApiError:
    return ApiError(413, "payload_too_large",
                    f"the frame is {'at least ' if at_least else ''}{size} bytes; the limit is {limit} bytes",
                    {"limit_bytes": limit})
