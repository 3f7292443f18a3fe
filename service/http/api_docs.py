"""/docs (Swagger UI) and /redoc (ReDoc), with their scripts and styles served by the app itself.

FastAPI's own pages load Swagger UI and ReDoc from a CDN, and ReDoc's fonts from a font service: without
internet both pages stay blank. These are the same pages, built with FastAPI's helpers, pointed at the bundles
that the fastapi-offline package ships, served under /docs/assets. The app is created with
``docs_url=None, redoc_url=None`` so that FastAPI adds none of its own.

The pages keep FastAPI's access rule (public, as /openapi.json is) and its handling of a proxy's root path.
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

DOCS_URL = "/docs"
REDOC_URL = "/redoc"
ASSETS_URL = "/docs/assets"
# Swagger UI's swagger-ui-bundle.js and swagger-ui.css, ReDoc's redoc.standalone.js and a favicon.
ASSETS_PACKAGE = ("fastapi_offline", "static")


def _root_path(request: Request) -> str:
    return request.scope.get("root_path", "").rstrip("/")


def install_api_docs(app: FastAPI) -> None:
    """Add /docs, its OAuth2 redirect page, /redoc and the /docs/assets files to ``app``."""
    app.mount(ASSETS_URL, StaticFiles(packages=[ASSETS_PACKAGE]), name="docs-assets")
    openapi_url = app.openapi_url
    redirect_url = app.swagger_ui_oauth2_redirect_url

    async def swagger_ui(request: Request) -> HTMLResponse:
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

    async def redoc(request: Request) -> HTMLResponse:
        root = _root_path(request)
        return get_redoc_html(
            openapi_url=root + openapi_url, title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}{ASSETS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{ASSETS_URL}/favicon.png", with_google_fonts=False)

    app.add_route(DOCS_URL, swagger_ui, include_in_schema=False)
    if redirect_url:
        app.add_route(redirect_url, swagger_ui_redirect, include_in_schema=False)
    app.add_route(REDOC_URL, redoc, include_in_schema=False)
