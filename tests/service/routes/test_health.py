"""/health and /ready: liveness without auth; readiness naming what is down, each probe with its timeout."""

from __future__ import annotations

import http.server
import socket
import threading
import time

import pytest
from fastapi.testclient import TestClient

from service.routes import health
from service.schemas import DependencyCheck

OK = DependencyCheck(status="ok", detail="fine")
DOWN = DependencyCheck(status="down", detail="connection refused")


def closed_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture
def ready_client(make_app):
    """``ready_client(redis=..., mlflow=..., workers=...)``: a client whose /ready uses these probe answers
    (``workers``: host names, or an exception the ping raises)."""

    def build(redis=OK, mlflow=OK, workers=("celery@box",)):
        app = make_app(public=(health.router,), api_key="secret")

        def ping():
            if isinstance(workers, Exception):
                raise workers
            return list(workers)

        app.dependency_overrides[health.get_probes] = lambda: health.Probes(
            redis=lambda settings: redis, mlflow=lambda settings: mlflow, workers=ping)
        return TestClient(app)

    return build


def test_health_is_ok_without_an_api_key(make_app):
    client = TestClient(make_app(public=(health.router,), api_key="secret"))
    response = client.get("/health")
    assert (response.status_code, response.json()) == (200, {"status": "ok"})


def test_ready_when_everything_answers(ready_client):
    response = ready_client().get("/ready")
    assert response.status_code == 200
    assert response.json() == {"status": "ready", "redis": OK.model_dump(), "mlflow": OK.model_dump(),
                               "workers": ["celery@box"], "workers_detail": "1 Celery worker answered ping",
                               "down": []}


def test_redis_down_is_503_and_workers_are_not_pinged(ready_client):
    response = ready_client(redis=DOWN, workers=AssertionError("must not ping")).get("/ready")
    assert response.status_code == 503
    body = response.json()
    assert body["status"] == "unavailable" and body["down"] == ["redis", "workers"]
    assert body["redis"] == DOWN.model_dump() and body["workers_detail"].startswith("not checked: Redis")


@pytest.mark.parametrize("workers, detail", [
    ((), "no Celery worker answered ping within 1 s"),
    (ConnectionError("broker gone"), "worker ping failed: ConnectionError: broker gone"),
])
def test_no_workers_is_503(ready_client, workers, detail):
    response = ready_client(workers=workers).get("/ready")
    assert response.status_code == 503
    assert response.json()["down"] == ["workers"] and response.json()["workers_detail"] == detail


def test_mlflow_down_is_503(ready_client):
    body = ready_client(mlflow=DOWN).get("/ready").json()
    assert body["down"] == ["mlflow"] and body["mlflow"]["status"] == "down"


# --- the probes themselves ---------------------------------------------------------------------------------


def test_redis_probe_against_the_test_database(settings, redis_db):
    check = health.check_redis(settings)
    assert check.status == "ok" and check.detail.startswith("PING redis://127.0.0.1:6379/15 answered")


def test_redis_probe_down_is_quick_and_hides_the_password(settings):
    url = f"redis://user:hunter2@127.0.0.1:{closed_port()}/15"
    start = time.perf_counter()
    check = health.check_redis(settings.model_copy(update={"redis_url": url}))
    assert time.perf_counter() - start < 3
    assert check.status == "down" and "hunter2" not in check.detail and "user:***@127.0.0.1" in check.detail


def test_mlflow_sqlite_probe_checks_the_folder(settings, tmp_path):
    (settings.data_dir / "mlflow").mkdir(parents=True)
    assert health.check_mlflow(settings).status == "ok"  # default: sqlite under data_dir/mlflow
    missing = settings.model_copy(update={"tracking_uri": f"sqlite:///{tmp_path}/nowhere/mlflow.db"})
    check = health.check_mlflow(missing)
    assert check.status == "down" and check.detail.endswith("nowhere does not exist")
    (tmp_path / "file").write_text("x")
    not_a_folder = settings.model_copy(update={"tracking_uri": f"sqlite:///{tmp_path}/file/mlflow.db"})
    assert health.check_mlflow(not_a_folder).status == "down"
    other = settings.model_copy(update={"tracking_uri": "databricks://profile"})
    assert health.check_mlflow(other).status == "skipped"


class _Handler(http.server.BaseHTTPRequestHandler):
    status = 200

    def do_GET(self):  # noqa: N802 (http.server's naming)
        self.send_response(self.status if self.path == "/health" else 404)
        self.end_headers()
        self.wfile.write(b"OK")

    def log_message(self, *args):
        pass


@pytest.fixture
def mlflow_server():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


def test_mlflow_http_probe(settings, mlflow_server):
    uri = f"http://127.0.0.1:{mlflow_server.server_address[1]}"
    check = health.check_mlflow(settings.model_copy(update={"tracking_uri": uri + "/"}))
    assert check == DependencyCheck(status="ok", detail=f"GET {uri}/health answered 200")
    _Handler.status = 503
    try:
        assert health.check_mlflow(settings.model_copy(update={"tracking_uri": uri})).detail.endswith("answered 503")
    finally:
        _Handler.status = 200
    closed = settings.model_copy(update={"tracking_uri": f"http://127.0.0.1:{closed_port()}"})
    check = health.check_mlflow(closed)
    assert check.status == "down" and "ConnectError" in check.detail


def test_readiness_schema_has_examples(make_app):
    document = TestClient(make_app(public=(health.router,))).get("/openapi.json").json()
    assert "503" in document["paths"]["/ready"]["get"]["responses"]
    assert document["components"]["schemas"]["Readiness"]["examples"]


def test_worker_ping_goes_through_the_celery_app(settings, redis_db):
    workers = health.ping_workers()  # nobody listens on the test database: an empty answer after the timeout
    assert isinstance(workers, list) and all(isinstance(name, str) for name in workers)
