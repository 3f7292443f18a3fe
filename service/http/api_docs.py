"""/docs (Swagger UI) and /redoc (ReDoc), with their scripts and styles served by the app itself.

FastAPI's own pages load Swagger UI and ReDoc from a CDN, and ReDoc's fonts from a font service: without
internet both pages stay blank. These are the same pages, built with FastAPI's helpers, pointed at the bundles
that the fastapi-offline package ships, served under /docs/assets. The app is created with
``openapi_url=None, docs_url=None, redoc_url=None`` so that FastAPI adds none of its own.

Access: with an API key configured (and DENOISER_PUBLIC_API_DOCS off) /openapi.json, both pages and their files
need it like every other route; without a key (local use) they are open. A browser cannot send X-API-Key, so a
page opened without it answers 401 with a form for the key. The form posts the key in its body (never in a URL,
which access logs and browser history keep) to /docs/key, which sets a cookie holding an HMAC of the key, not the
key, that only these routes accept, and sends the browser back to the page. Every other route ignores the cookie.
The pages keep FastAPI's handling of a proxy's root path.
"""

from __future__ import annotations

import hashlib
import hmac
from html import escape
from typing import Annotated
from urllib.parse import parse_qs

from fastapi import Depends, FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles

from core.settings import Settings, get_settings
from service.http.auth import API_KEY_HEADER
from service.http.errors import ApiError

DOCS_URL = "/docs"
REDOC_URL = "/redoc"
ASSETS_URL = "/docs/assets"
OPENAPI_URL = "/openapi.json"
KEY_URL = "/docs/key"
DOCS_COOKIE = "denoiser_api_docs"
COOKIE_SECONDS = 8 * 3600
KEY_FORM_BYTES = 4096  # the key form's body: a key and a page name
# Swagger UI's swagger-ui-bundle.js and swagger-ui.css, ReDoc's redoc.standalone.js and a favicon.
ASSETS_PACKAGE = ("fastapi_offline", "static")


def _root_path(request: Request) -> str:
    return request.scope.get("root_path", "").rstrip("/")


SettingsDep = Annotated[Settings, Depends(get_settings)]


def docs_cookie(api_key: str) -> str:
    """The cookie's value: opens the docs only, tells nothing of the key, and a new key voids it."""
    return hmac.new(api_key.encode(), b"denoiser-service api docs", hashlib.sha256).hexdigest()


def _matches(given: str | None, expected: str) -> bool:
    return given is not None and hmac.compare_digest(given.encode(), expected.encode())


def docs_open(request: Request, settings: Settings) -> bool:
    """Whether ``request`` may read the schema and the docs pages (see the module's docstring)."""
    if settings.api_key is None or settings.public_api_docs:
        return True
    return (_matches(request.headers.get(API_KEY_HEADER), settings.api_key)
            or _matches(request.cookies.get(DOCS_COOKIE), docs_cookie(settings.api_key)))


def require_docs_access(request: Request, settings: SettingsDep) -> None:
    if not docs_open(request, settings):
        raise ApiError(401, "unauthorized", f"the API docs need this server's API key: send {API_KEY_HEADER}, or "
                                            f"open {DOCS_URL} in a browser and enter the key",
                       headers={"WWW-Authenticate": "APIKey"})


def _key_form(request: Request, page: str, message: str) -> HTMLResponse:
    """401 with a form asking for the key, posted to /docs/key (no script, nothing from another host)."""
    html = (f'<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>API key</title></head><body>\n'
            f'<form method="post" action="{escape(_root_path(request) + KEY_URL)}">\n<p>{escape(message)}</p>\n'
            f'<input type="hidden" name="next" value="{escape(page)}">\n'
            f'<label>{API_KEY_HEADER} <input type="password" name="api_key" autocomplete="current-password" '
            f'autofocus></label>\n<button type="submit">Open</button>\n</form></body></html>\n')
    return HTMLResponse(html, status_code=401, headers={"WWW-Authenticate": "APIKey"})


async def _form_fields(request: Request) -> dict[str, str]:
    body = b""
    async for chunk in request.stream():
        body += chunk
        if len(body) > KEY_FORM_BYTES:
            raise ApiError(413, "payload_too_large", f"the key form takes at most {KEY_FORM_BYTES} bytes")
    return {name: values[0] for name, values in parse_qs(body.decode("utf-8", "replace")).items()}


def install_api_docs(app: FastAPI) -> None:
    """Add /openapi.json, /docs, its OAuth2 redirect page, /redoc, the /docs/assets files and /docs/key to ``app``
    (created with ``openapi_url=None``: FastAPI's own schema route would be public)."""
    assets = StaticFiles(packages=[ASSETS_PACKAGE])
    openapi_url = OPENAPI_URL
    redirect_url = app.swagger_ui_oauth2_redirect_url
    guarded = [Depends(require_docs_access)]
    refused = "This server's API docs need its API key."

    async def openapi(request: Request) -> JSONResponse:
        # As FastAPI's own schema route: behind a proxy prefix, the prefix is the first server.
        root = _root_path(request)
        schema = app.openapi()
        if root and app.root_path_in_servers and root not in {s.get("url") for s in schema.get("servers", [])}:
            schema = {**schema, "servers": [{"url": root}, *schema.get("servers", [])]}
        return JSONResponse(schema)

    async def asset(name: str, request: Request) -> Response:
        return await assets.get_response(name, request.scope)

    async def docs_key(request: Request, settings: SettingsDep) -> Response:
        fields = await _form_fields(request)
        # Back to one of the two pages only: the form cannot send a browser elsewhere.
        page = fields.get("next") if fields.get("next") in (DOCS_URL, REDOC_URL) else DOCS_URL
        root = _root_path(request)
        if settings.api_key is None or settings.public_api_docs:
            return RedirectResponse(root + page, status_code=303)
        if not _matches(fields.get("api_key"), settings.api_key):
            return _key_form(request, page, f"That key does not match this server's API key. {refused}")
        response = RedirectResponse(root + page, status_code=303)
        response.set_cookie(DOCS_COOKIE, docs_cookie(settings.api_key), max_age=COOKIE_SECONDS, path=root or "/",
                            httponly=True, samesite="strict", secure=request.url.scheme == "https")
        return response

    async def swagger_ui(request: Request, settings: SettingsDep) -> HTMLResponse:
        if not docs_open(request, settings):
            return _key_form(request, DOCS_URL, refused)
        root = _root_path(request)
        return get_swagger_ui_html(
            openapi_url=root + openapi_url, title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=root + redirect_url if redirect_url else None,
            init_oauth=app.swagger_ui_init_oauth, swagger_ui_parameters=app.swagger_ui_parameters,
            swagger_js_url=f"{root}{ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{root}{ASSETS_URL}/favicon.png")

    async def swagger_ui_redirect(request: Request) -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    async def redoc(request: Request, settings: SettingsDep) -> HTMLResponse:
        if not docs_open(request, settings):
            return _key_form(request, REDOC_URL, refused)
        root = _root_path(request)
        return get_redoc_html(
            openapi_url=root + openapi_url, title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}{ASSETS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{ASSETS_URL}/favicon.png", with_google_fonts=False)

    app.add_api_route(openapi_url, openapi, include_in_schema=False, dependencies=guarded)
    app.add_api_route(f"{ASSETS_URL}/{{name}}", asset, include_in_schema=False, dependencies=guarded)
    app.add_api_route(KEY_URL, docs_key, methods=["POST"], include_in_schema=False)
    app.add_api_route(DOCS_URL, swagger_ui, include_in_schema=False)
    if redirect_url:
        app.add_api_route(redirect_url, swagger_ui_redirect, include_in_schema=False, dependencies=guarded)
    app.add_api_route(REDOC_URL, redoc, include_in_schema=False)
