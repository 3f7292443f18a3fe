"""/docs and /redoc without internet: the pages name only the app's own files, those files are served, and a
real headless Chromium (Debian's package; `scripts/install.sh --browser`) renders the operations from them with
every host but 127.0.0.1 unresolvable."""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
import threading
from collections.abc import Iterator
from html import escape

import pytest
import uvicorn
from fastapi.testclient import TestClient

from core.settings import get_settings
from service.http.api_docs import ASSETS_URL

PAGE_ASSETS = {
    "/docs": {f"{ASSETS_URL}/swagger-ui-bundle.js", f"{ASSETS_URL}/swagger-ui.css", f"{ASSETS_URL}/favicon.png"},
    "/redoc": {f"{ASSETS_URL}/redoc.standalone.js", f"{ASSETS_URL}/favicon.png"},
}
CONTENT_TYPES = {".js": ("text/javascript", "application/javascript"), ".css": ("text/css",),
                 ".png": ("image/png",)}


def referenced_urls(html: str) -> set[str]:
    return set(re.findall(r'(?:src|href)="([^"]*)"', html))


@pytest.mark.parametrize("page", sorted(PAGE_ASSETS))
def test_a_docs_page_names_only_the_apps_own_files_and_they_are_served(app, page):
    client = TestClient(app)
    response = client.get(page)
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/html")
    assert "://" not in response.text  # no CDN, no font service: nothing on another host
    assert referenced_urls(response.text) == PAGE_ASSETS[page]
    for url in PAGE_ASSETS[page]:
        asset = client.get(url)
        assert asset.status_code == 200, url
        assert asset.headers["content-type"].split(";")[0] in CONTENT_TYPES[url[url.rindex("."):]], url
        assert len(asset.content) > 1000, url


def test_behind_a_proxy_prefix_the_pages_name_the_prefixed_files(app):
    client = TestClient(app, root_path="/api")
    for page, assets in PAGE_ASSETS.items():
        html = client.get(page).text
        assert referenced_urls(html) == {f"/api{url}" for url in assets}
        assert "/api/openapi.json" in html


def test_the_docs_stay_public_like_the_openapi_document_when_a_key_is_required(app, settings):
    keyed = settings.model_copy(update={"api_key": "0123456789abcdef0123456789abcdef"})
    app.dependency_overrides[get_settings] = lambda: keyed
    client = TestClient(app)
    assert client.get("/datasets").status_code == 401  # the key is required
    for url in ["/openapi.json", "/docs", "/redoc", "/docs/oauth2-redirect", *PAGE_ASSETS["/docs"]]:
        assert client.get(url).status_code == 200, url


def test_the_docs_pages_are_not_operations_of_the_api(app):
    paths = app.openapi()["paths"]
    assert not [path for path in paths if path.startswith(("/docs", "/redoc"))]


# --- a real browser ---------------------------------------------------------------------------------------

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="Chromium is not installed (scripts/install.sh --browser installs Debian's chromium)")


@pytest.fixture
def served(app) -> Iterator[str]:
    """The app on a free port of 127.0.0.1, in a thread (lifespan off: the pages need no session store)."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(app, lifespan="off", log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    while not server.started and thread.is_alive():
        thread.join(0.05)
    assert server.started, "uvicorn did not start"
    yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    server.should_exit = True
    thread.join(30)
    sock.close()


def rendered_dom(url: str, profile) -> str:
    """The page's DOM after its scripts ran, with every host but 127.0.0.1 unresolvable (no internet)."""
    result = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={profile}",
         "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1", "--virtual-time-budget=10000",
         "--dump-dom", url],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


@needs_chromium
def test_swagger_ui_and_redoc_render_the_operations_offline(app, served, tmp_path):
    summary = escape(app.openapi()["paths"]["/sessions"]["post"]["summary"])
    swagger = rendered_dom(f"{served}/docs", tmp_path / "profile")
    assert 'class="opblock ' in swagger and 'data-path="/sessions"' in swagger
    assert summary in swagger
    redoc = rendered_dom(f"{served}/redoc", tmp_path / "profile")
    assert 'id="operation/' in redoc and summary in redoc
