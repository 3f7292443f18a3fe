"""The one JSON error shape of the API: {"error": {"code", "message", "details"}}.

Routes raise ApiError (or its helpers) for the caller's mistakes; request validation errors, HTTP errors
from Starlette (404 for unknown paths, 405) and library errors that mean bad input (FrameError, DatasetError)
are all turned into that shape here. Anything else is a bug and answers 500 with the same shape.
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

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


def error_body(code: str, message: str, details: Any = None) -> dict:
    return {"error": {"code": code, "message": message, "details": details}}


def _status_code_name(status: int) -> str:
    return {400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found",
            405: "method_not_allowed", 409: "conflict", 413: "payload_too_large", 415: "unsupported_media_type",
            422: "invalid_request", 429: "too_many_requests"}.get(status, f"http_{status}")


def _allowed_methods(request: Request) -> str:
    """Every method of every route whose path matches the request's. Starlette's 405 names only the methods of
    the first route matching the path, while one path (e.g. /datasets/{id}) has a route per method."""
    methods: set[str] = set()
    for route in request.app.router.routes:
        match, _ = route.matches(request.scope)
        if match != Match.NONE:
            methods |= getattr(route, "methods", None) or set()
    return ", ".join(sorted(methods))


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(ApiError)
    async def _api_error(request: Request, error: ApiError) -> JSONResponse:
        return JSONResponse(error_body(error.code, error.message, error.details), status_code=error.status,
                            headers=error.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, error: RequestValidationError) -> JSONResponse:
        problems = [{"location": ".".join(str(part) for part in e.get("loc", ())), "message": e.get("msg", ""),
                     "type": e.get("type", "")} for e in error.errors()]
        summary = "; ".join(f"{p['location']}: {p['message']}" for p in problems[:5])
        return JSONResponse(error_body("invalid_request", f"invalid request: {summary}", problems), status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, error: StarletteHTTPException) -> JSONResponse:
        message = error.detail if isinstance(error.detail, str) else str(error.detail)
        headers = getattr(error, "headers", None)
        if error.status_code == 405:
            headers = {**(headers or {}), "Allow": _allowed_methods(request)}
        return JSONResponse(error_body(_status_code_name(error.status_code), message), status_code=error.status_code,
                            headers=headers)

    from model.dataset import DatasetError
    from model.frames import FrameError

    @app.exception_handler(FrameError)
    async def _frame_error(request: Request, error: FrameError) -> JSONResponse:
        return JSONResponse(error_body("invalid_frame", str(error)), status_code=400)

    @app.exception_handler(DatasetError)
    async def _dataset_error(request: Request, error: DatasetError) -> JSONResponse:
        return JSONResponse(error_body("invalid_dataset", str(error)), status_code=400)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, error: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return JSONResponse(error_body("internal_error", f"internal error: {type(error).__name__}: {error}"),
                            status_code=500)
