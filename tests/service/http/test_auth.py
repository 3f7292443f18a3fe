"""An API reachable from other machines refuses to start without a real key: `denoiser serve --host`, the app's
start (DENOISER_REQUIRE_API_KEY, which docker-compose sets) and the key checks themselves."""

from __future__ import annotations

import pytest
import uvicorn
from fastapi.testclient import TestClient

from core.deployment import check_deployment_key, deployment_key_problem, is_loopback
from cli.main import main

REAL_KEY = "0123456789abcdef0123456789abcdef"


@pytest.mark.parametrize(("host", "loopback"), [("127.0.0.1", True), ("localhost", True), ("::1", True),
                                                ("[::1]", True), ("0.0.0.0", False), ("::", False),
                                                ("192.168.1.4", False), ("api.example.org", False)])
def test_loopback_hosts(host, loopback):
    assert is_loopback(host) is loopback


@pytest.mark.parametrize(("key", "problem"), [(None, "is not set"), ("  ", "is not set"),
                                              ("change-me", "the placeholder 'change-me'"),
                                              ("Secret", "the placeholder"), ("short-but-mine", "fewer than 16"),
                                              (REAL_KEY, None)])
def test_deployment_key_problems(key, problem):
    found = deployment_key_problem(key)
    assert (found is None) if problem is None else (problem in found)


def test_the_check_applies_only_beyond_localhost_or_when_required(settings):
    check_deployment_key(settings, "127.0.0.1")  # local development without a key
    with pytest.raises(RuntimeError, match="refusing to serve on 0.0.0.0: DENOISER_API_KEY is not set"):
        check_deployment_key(settings, "0.0.0.0")
    with pytest.raises(RuntimeError, match="with DENOISER_REQUIRE_API_KEY set: DENOISER_API_KEY is the placeholder"):
        check_deployment_key(settings.model_copy(update={"require_api_key": True, "api_key": "change-me"}))
    check_deployment_key(settings.model_copy(update={"api_key": REAL_KEY}), "0.0.0.0")


def test_serve_beyond_localhost_without_a_key_exits_2_before_starting(settings, monkeypatch, capsys):
    started = []
    monkeypatch.setattr(uvicorn, "run", lambda *args, **kwargs: started.append(kwargs))
    assert main(["serve", "--host", "0.0.0.0"]) == 2
    assert "DENOISER_API_KEY is not set" in capsys.readouterr().err
    monkeypatch.setenv("DENOISER_API_KEY", "change-me")
    settings_cache_clear()
    assert main(["serve", "--host", "0.0.0.0"]) == 2
    assert started == []
    assert main(["serve", "--host", "127.0.0.1"]) == 0 and started[0]["host"] == "127.0.0.1"


def settings_cache_clear() -> None:
    from core.settings import get_settings

    get_settings.cache_clear()


def test_the_app_refuses_to_start_with_a_placeholder_key_when_required(settings, monkeypatch):
    from service.http.app import create_app

    monkeypatch.setenv("DENOISER_REQUIRE_API_KEY", "true")
    monkeypatch.setenv("DENOISER_API_KEY", "change-me")
    settings_cache_clear()
    with pytest.raises(RuntimeError, match="placeholder 'change-me'"), TestClient(create_app()):
        pass


def test_with_a_key_the_schema_and_the_docs_are_not_public_unless_asked(settings, monkeypatch):
    from service.http.app import create_app

    monkeypatch.setenv("DENOISER_API_KEY", REAL_KEY)
    settings_cache_clear()
    client = TestClient(create_app())  # no lifespan: these routes need no session store
    for url in ("/openapi.json", "/docs", "/redoc"):
        assert client.get(url).status_code == 401, url
        assert client.get(url, headers={"X-API-Key": REAL_KEY}).status_code == 200, url
    assert client.get("/health").status_code == 200
    monkeypatch.setenv("DENOISER_PUBLIC_API_DOCS", "true")
    settings_cache_clear()
    for url in ("/openapi.json", "/docs", "/redoc"):
        assert client.get(url).status_code == 200, url
    assert client.get("/models").status_code == 401
