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
from tests.builders import error_message

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


KEY = "0123456789abcdef0123456789abcdef"
DOCS_URLS = ["/openapi.json", "/docs", "/redoc", "/docs/oauth2-redirect", *sorted(PAGE_ASSETS["/docs"]),
             *sorted(PAGE_ASSETS["/redoc"])]


def keyed_client(app, settings, **changes) -> TestClient:
    keyed = settings.model_copy(update={"api_key": KEY, **changes})
    app.dependency_overrides[get_settings] = lambda: keyed
    return TestClient(app)


def test_with_a_key_the_schema_the_pages_and_their_files_need_it(app, settings):
    client = keyed_client(app, settings)
    for url in DOCS_URLS:
        assert client.get(url).status_code == 401, url
        assert client.get(url, headers={"X-API-Key": "not" + KEY}).status_code == 401, url
        assert client.get(url, headers={"X-API-Key": KEY}).status_code == 200, url
    assert "X-API-Key" in error_message(client.get("/openapi.json"), 401, "unauthorized")


@pytest.mark.parametrize("page", sorted(PAGE_ASSETS))
def test_a_browser_enters_the_key_once_and_reads_the_docs_by_a_cookie_that_opens_nothing_else(app, settings, page):
    client = keyed_client(app, settings)
    asked = client.get(page)
    assert asked.status_code == 401 and asked.headers["content-type"].startswith("text/html")
    assert '<form method="post" action="/docs/key">' in asked.text and "://" not in asked.text
    wrong = client.post("/docs/key", data={"api_key": "not" + KEY, "next": page}, follow_redirects=False)
    assert wrong.status_code == 401 and "does not match" in wrong.text and not client.cookies
    entered = client.post("/docs/key", data={"api_key": KEY, "next": page}, follow_redirects=False)
    assert (entered.status_code, entered.headers["location"]) == (303, page)
    cookie = entered.headers["set-cookie"]
    assert KEY not in cookie and "HttpOnly" in cookie and "SameSite=strict" in cookie
    for url in [page, "/openapi.json", *PAGE_ASSETS[page]]:
        assert client.get(url).status_code == 200, url
    assert client.get("/datasets").status_code == 401  # the cookie is no API key


def test_the_key_form_sends_the_browser_only_to_a_docs_page(app, settings):
    client = keyed_client(app, settings)
    answer = client.post("/docs/key", data={"api_key": KEY, "next": "https://elsewhere.example/"},
                         follow_redirects=False)
    assert answer.headers["location"] == "/docs"
    error_message(client.post("/docs/key", content=b"api_key=" + b"x" * 5000,
                              headers={"Content-Type": "application/x-www-form-urlencoded"}), 413, "payload_too_large")


def test_public_api_docs_opens_the_docs_but_not_the_api(app, settings):
    client = keyed_client(app, settings, public_api_docs=True)
    assert client.get("/datasets").status_code == 401
    for url in DOCS_URLS:
        assert client.get(url).status_code == 200, url


def test_without_a_key_the_docs_are_open(app):
    client = TestClient(app)
    for url in DOCS_URLS:
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
