"""The one JSON error shape of the API: {"error": {"code", "message", "details"}}, and the one table where errors
of the domain become HTTP status codes (``ERROR_STATUS``), which every route uses.

Routes raise ApiError (or its helpers) for the caller's mistakes; core, the registry, the job store, sessions and
uploads raise their own errors, translated by the table (a handler of the app, or ``domain_errors`` where a route
needs the ApiError itself). Those, request validation errors, HTTP errors from Starlette (404 for unknown paths,
405) and library errors that mean bad input (FrameError, DatasetError) all get that shape here. Anything else is a
bug and answers 500 with the same shape.
"""

from __future__ import annotations

import errno
import logging
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from core.errors import Conflict, Invalid, NotFound, Unavailable
from core.job_store import JobFinished, JobNotFound
from core.registry import ConstraintNotMet, NoAutoCandidates, RegistryUnavailable, UnknownModelError
from model.io.dataset import DatasetError
from model.io.exr import DecodeTooLarge, FrameTooLarge
from model.io.frames import FrameError
from service.datasets import errors as upload
from service.sessions import store as sessions
from service.sessions.models import SessionModelInvalid, SessionModelNotFound
from client.codec import StreamFrameTooLarge, StreamMessageError

log = logging.getLogger("denoiser.api")


class ApiError(Exception):
    def __init__(self, status: int, code: str, message: str, details: Any = None,
                 headers: dict[str, str] | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.details = details
        self.headers = headers


def not_found(what: str, identifier: str) -> ApiError:
    return ApiError(404, "not_found", f"{what} {identifier!r} does not exist")


def bad_request(message: str, details: Any = None, code: str = "bad_request") -> ApiError:
    return ApiError(400, code, message, details)


def conflict(message: str, details: Any = None, code: str = "conflict") -> ApiError:
    return ApiError(409, code, message, details)


# Error class -> (HTTP status, error code). The nearest class of an error's MRO decides; the code is the error's own
# ``code`` when it has one (None here), the message its ``message`` (else its text), the details its ``details``.
ERROR_STATUS: dict[type[Exception], tuple[int, str | None]] = {
    # core.errors: job checks, the worker's refusals
    NotFound: (404, None), Invalid: (422, None), Conflict: (409, None), Unavailable: (503, None),
    # the model registry and its automatic choice
    UnknownModelError: (404, "not_found"), RegistryUnavailable: (503, "registry_unavailable"),
    NoAutoCandidates: (404, "no_candidate_model"), ConstraintNotMet: (422, "constraint_not_met"),
    # the job store
    JobNotFound: (404, "not_found"), JobFinished: (409, "job_finished"),
    # sessions and the models they open
    SessionModelNotFound: (404, "not_found"), SessionModelInvalid: (422, None),
    sessions.SessionNotFound: (404, None), sessions.FrameRejected: (409, None),
    sessions.SessionLimitReached: (429, None), sessions.ModelNotLoadable: (422, None),
    sessions.SessionStoreUnavailable: (503, None),
    # dataset uploads
    upload.UploadError: (400, None), upload.InvalidUpload: (400, None), upload.UnknownDataset: (404, None),
    upload.UploadConflict: (409, None), upload.UploadTooLarge: (413, None), upload.FrameTooLargeUpload: (413, None),
    # frames and datasets the caller sent
    FrameError: (400, "invalid_frame"), FrameTooLarge: (413, "frame_too_large"), DatasetError: (400, "invalid_dataset"),
    StreamMessageError: (400, None), StreamFrameTooLarge: (413, None),
    # Any other library refusal of the input, inside ``domain_errors`` only: elsewhere a ValueError is a bug (500).
    ValueError: (422, "invalid_request"),
}
_ONLY_INSIDE_ROUTES = (ValueError,)


def api_error(error: Exception, details: Any = None) -> ApiError | None:
    """``error`` as the ApiError the table gives it (``details``: instead of the error's own), None when the table
    has no class of it."""
    for cls in type(error).__mro__:
        if cls in ERROR_STATUS:
            status, code = ERROR_STATUS[cls]
            message = getattr(error, "message", None) or str(error)
            return ApiError(status, getattr(error, "code", None) or code, message,
                            details if details is not None else getattr(error, "details", None))
    return None


def frame_error_details(error: FrameError) -> dict:
    """The details the frame routes give a refused frame: the pixels and the limit of one too large, else the buffer
    and the problem."""
    if isinstance(error, DecodeTooLarge):
        return {"decoded_bytes": error.pixels, "limit_bytes": error.limit}
    if isinstance(error, FrameTooLarge):
        return {"pixels": error.pixels, "limit_pixels": error.limit}
    return {"buffer": error.buffer, "problem": error.problem}


@contextmanager
def domain_errors() -> Iterator[None]:
    """Errors of the table raised inside as their ApiError (for a route that hands it on, e.g. over a WebSocket,
    or one where a ValueError means the caller's input)."""
    try:
        yield
    except ApiError:
        raise
    except Exception as error:
        translated = api_error(error)
        if translated is None:
            raise
        raise translated from None


def error_body(code: str, message: str, details: Any = None) -> dict:
    return {"error": {"code": code, "message": message, "details": details}}


def documented_error(description: str, code: str, message: str) -> dict:
    """One entry of a route's OpenAPI ``responses``: what the status means and an example body in the one shape."""
    return {"description": description, "content": {"application/json": {"example": error_body(code, message)}}}


INVALID_JSON = "invalid_json"
FASTAPI_BODY_PARSE_ERROR = "There was an error parsing the body"
_NOT_AN_OBJECT = {"model_attributes_type", "dict_type", "model_type"}


def _body_problem(request: Request, errors: list[dict]) -> tuple[int, str, str, Any] | None:
    """A JSON body that is not JSON, or not sent as JSON, as (status, code, message, details); None otherwise.

    FastAPI reports both as validation errors of the body (422 "JSON decode error", "Input should be a valid
    dictionary"), which do not tell the caller what to change.
    """
    for problem in errors:
        location = tuple(problem.get("loc", ()))
        if not location or location[0] != "body":
            continue
        if problem.get("type") == "json_invalid":
            position = location[1] if len(location) > 1 else None
            reason = (problem.get("ctx") or {}).get("error")
            where = f" at character {position}" if isinstance(position, int) else ""
            return (400, INVALID_JSON, f"the body is not valid JSON{where}" + (f": {reason}" if reason else ""),
                    {"position": position})
        if location == ("body",) and problem.get("type") in _NOT_AN_OBJECT:
            declared = request.headers.get("content-type")
            media_type = declared.split(";")[0].strip().lower() if declared else None
            if media_type != "application/json":
                sent = f"Content-Type {media_type} is not accepted here" if media_type else "no Content-Type"
                return (415, "unsupported_media_type",
                        f"{sent}; send the body as JSON with Content-Type application/json",
                        {"received": media_type, "accepted": ["application/json"]})
    return None


def _unparsable_body(cause: BaseException | None) -> str:
    """Why FastAPI could not parse a JSON body (it keeps the parser's exception as the cause)."""
    if isinstance(cause, UnicodeDecodeError):
        return "the body could not be read as JSON text: it is not UTF-8"
    if isinstance(cause, RecursionError):
        return "the body is not accepted as JSON: it is nested too deeply"
    if isinstance(cause, ValueError) and "digits" in str(cause):
        return f"the body is not accepted as JSON: an integer has too many digits ({cause})"
    return "the body could not be read as JSON text"


def _status_code_name(status: int) -> str:
    return {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found",
            405: "method_not_allowed", 409: "conflict", 413: "payload_too_large", 415: "unsupported_media_type",
            422: "invalid_request", 429: "too_many_requests"}.get(status, f"http_{status}")


def _allowed_methods(request: Request) -> str:
    """Every method of every route whose path matches the request's. Starlette's 405 names only the methods of
    the first route matching the path, while one path (e.g. /datasets/{id}) has a route per method."""
    methods: set[str] = set()
    for route in _endpoint_routes(request.app.router.routes):
        match, _ = route.matches(request.scope)
        if match != Match.NONE:
            methods |= getattr(route, "methods", None) or set()
    return ", ".join(sorted(methods))


def _endpoint_routes(routes: list) -> list:
    """The routes that answer requests, with included routers opened: FastAPI 0.16x keeps an included router as
    one wrapper route (its ``original_router`` holds the routes, with their full paths) that has no methods."""
    found = []
    for route in routes:
        inner = getattr(route, "original_router", None)
        if inner is not None:
            found += _endpoint_routes(inner.routes)
        else:
            found.append(route)
    return found


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, error: ApiError) -> JSONResponse:
        return JSONResponse(error_body(error.code, error.message, error.details), status_code=error.status,
                            headers=error.headers)

    async def _table_error(request: Request, error: Exception) -> JSONResponse:
        return await _api_error(request, api_error(error))

    for error_class in ERROR_STATUS:
        if error_class not in _ONLY_INSIDE_ROUTES:
            app.add_exception_handler(error_class, _table_error)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, error: RequestValidationError) -> JSONResponse:
        errors = error.errors()
        body_problem = _body_problem(request, errors)
        if body_problem is not None:
            return JSONResponse(error_body(*body_problem[1:]), status_code=body_problem[0])
        problems = [{"location": ".".join(str(part) for part in e.get("loc", ())), "message": e.get("msg", ""),
                     "type": e.get("type", "")} for e in errors]
        summary = "; ".join(f"{p['location']}: {p['message']}" for p in problems[:5])
        return JSONResponse(error_body("invalid_request", f"invalid request: {summary}", problems), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, error: StarletteHTTPException) -> JSONResponse:
        message = error.detail if isinstance(error.detail, str) else str(error.detail)
        headers = getattr(error, "headers", None)
        if error.status_code == 400 and message == FASTAPI_BODY_PARSE_ERROR:
            if isinstance(error.__cause__, ApiError):  # e.g. the body read timed out (service.http.request_limits)
                return await _api_error(request, error.__cause__)
            return JSONResponse(error_body(INVALID_JSON, _unparsable_body(error.__cause__)), status_code=400)
        if error.status_code == 405:
            allowed = _allowed_methods(request)
            headers = {**(headers or {}), "Allow": allowed}
            message = f"{request.method} is not allowed on {request.url.path}; allowed: {allowed or 'none'}"
        return JSONResponse(error_body(_status_code_name(error.status_code), message), status_code=error.status_code,
                            headers=headers)

    @app.exception_handler(OSError)
    async def _storage_error(request: Request, error: OSError) -> JSONResponse:
        return _os_error_response(request, error)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, error: Exception) -> JSONResponse:
        return _internal_error(request, error)


# Storage that cannot take a write: the server's condition, not the caller's mistake, and not a bug either.
STORAGE_FULL_ERRNOS = {errno.ENOSPC: "no space left", errno.EDQUOT: "disk quota exceeded",
                       errno.EROFS: "storage is read-only", errno.EACCES: "storage is not writable",
                       errno.EPERM: "storage is not writable"}


def _os_error_response(request: Request, error: OSError) -> JSONResponse:
    """507 for storage that is full or read-only, with a neutral message (paths go to the log only); any other
    OSError is an internal error."""
    reason = STORAGE_FULL_ERRNOS.get(error.errno) if error.errno is not None else None
    if reason is None:
        return _internal_error(request, error)
    reference = uuid.uuid4().hex[:12]
    log.error("storage error %s on %s %s: %s (path %s)", reference, request.method, request.url.path, error,
              error.filename)
    return JSONResponse(error_body("insufficient_storage", f"the server cannot store data now ({reason}); "
                                                           f"nothing was changed, retry later (reference "
                                                           f"{reference})", {"reference": reference}),
                        status_code=507, headers={"Retry-After": "60"})


def _internal_error(request: Request, error: Exception) -> JSONResponse:
    """500 naming the kind of failure and a reference to the log entry, never the message (it may hold paths)."""
    reference = uuid.uuid4().hex[:12]
    log.error("unhandled error %s on %s %s", reference, request.method, request.url.path, exc_info=error)
    return JSONResponse(error_body("internal_error", f"internal error ({type(error).__name__}); the server log "
                                                     f"has the details under reference {reference}",
                                   {"reference": reference}), status_code=500)
