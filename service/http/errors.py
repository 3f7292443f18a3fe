"""The one JSON error shape of the API: {"error": {"code", "message", "details"}}, and the one place where domain
errors become HTTP status codes (``DOMAIN_STATUS``).

Routes raise ApiError (or its helpers) for the caller's mistakes, core raises domain errors (``core.errors``);
those, request validation errors, HTTP errors from Starlette (404 for unknown paths, 405) and library errors that
mean bad input (FrameError, DatasetError) are all turned into that shape here. Anything else is a bug and answers 500 with the same shape.
"""

from __future__ import annotations

import errno
import logging
import uuid
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from core.errors import Conflict, DomainError, Invalid, NotFound, Unavailable

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


DOMAIN_STATUS: dict[type[DomainError], int] = {NotFound: 404, Invalid: 422, Conflict: 409, Unavailable: 503}


def status_of(error: DomainError) -> int:
    """The HTTP status of a domain error (its nearest class in ``DOMAIN_STATUS``; 422 for another)."""
    for cls in type(error).__mro__:
        if cls in DOMAIN_STATUS:
            return DOMAIN_STATUS[cls]
    return 422


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

    @app.exception_handler(DomainError)
    async def _domain_error(request: Request, error: DomainError) -> JSONResponse:
        return JSONResponse(error_body(error.code, error.message, error.details), status_code=status_of(error))

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

    from model.io.dataset import DatasetError
    from model.io.frames import FrameError

    @app.exception_handler(FrameError)
    async def _frame_error(request: Request, error: FrameError) -> JSONResponse:
        return JSONResponse(error_body("invalid_frame", str(error)), status_code=400)

    @app.exception_handler(DatasetError)
    async def _dataset_error(request: Request, error: DatasetError) -> JSONResponse:
        return JSONResponse(error_body("invalid_dataset", str(error)), status_code=400)

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
