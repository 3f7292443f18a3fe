"""/health and /ready: liveness without auth; readiness naming what is down, each probe with its timeout."""

from __future__ import annotations

import http.server
import threading
import time

import pytest
import redis
from fastapi.testclient import TestClient

from core.heartbeats import Heartbeat, WorkerBeat, read_beats
from core.redis_persistence import redis_persistence
from service.http.routes import health
from service.http.schemas.health import DependencyCheck
from tests.builders import closed_port

OK = DependencyCheck(status="ok", detail="fine")
DOWN = DependencyCheck(status="down", detail="connection refused")
BEAT = WorkerBeat("celery@box", 7, ["cpu"], None, 0.0)
BUSY = WorkerBeat("celery@box", 7, ["cpu"], "7f3c", 0.0)


@pytest.fixture
def ready_client(make_app):
    """``ready_client(redis=..., storage=..., mlflow=..., workers=...)``: a client whose /ready uses these probe
    answers (``workers``: heartbeats, or an exception reading them raises)."""

    def build(redis=OK, storage=OK, mlflow=OK, workers=(BEAT,), persistence="aof"):
        app = make_app(public=(health.router,), api_key="secret")

        def beats(settings):
            if isinstance(workers, Exception):
                raise workers
            return list(workers)

        app.dependency_overrides[health.get_probes] = lambda: health.Probes(
            redis=lambda settings: redis, storage=lambda settings: storage, mlflow=lambda settings: mlflow,
            workers=beats, persistence=lambda settings: persistence)
        return TestClient(app)

    return build


def test_health_is_ok_without_an_api_key(make_app):
    client = TestClient(make_app(public=(health.router,), api_key="secret"))
    response = client.get("/health")
    assert (response.status_code, response.json()) == (200, {"status": "ok"})


def test_ready_when_everything_answers(ready_client):
    response = ready_client().get("/ready")
    assert response.status_code == 200
    assert response.json() == {"status": "ready", "redis": OK.model_dump(), "storage": OK.model_dump(),
                               "mlflow": OK.model_dump(), "workers": ["celery@box"],
                               "workers_detail": "1 worker alive (heartbeat within 30 s); all idle", "down": [],
                               "redis_persistence": "aof", "warnings": []}


@pytest.mark.parametrize(("persistence", "warned"), [("aof", False), ("rdb", False), ("none", True),
                                                     ("unknown", True)])
def test_a_redis_without_persistence_is_a_warning_not_unready(ready_client, persistence, warned):
    response = ready_client(persistence=persistence).get("/ready")
    assert response.status_code == 200 and response.json()["status"] == "ready"
    body = response.json()
    assert body["redis_persistence"] == persistence and bool(body["warnings"]) is warned
    if persistence == "none":
        assert "a Redis restart empties the job queue" in body["warnings"][0]


def test_redis_down_leaves_its_persistence_unknown_and_unasked(ready_client):
    body = ready_client(redis=DOWN, workers=(), persistence=AssertionError("must not ask")).get("/ready").json()
    assert body["redis_persistence"] == "unknown" and body["warnings"] == []


def test_redis_down_is_503_and_heartbeats_are_not_read(ready_client):
    response = ready_client(redis=DOWN, workers=AssertionError("must not read")).get("/ready")
    assert response.status_code == 503
    body = response.json()
    assert body["status"] == "unavailable" and body["down"] == ["redis"]
    assert body["redis"] == DOWN.model_dump() and body["workers_detail"].startswith("not checked: Redis")


@pytest.mark.parametrize("workers, detail", [
    ((), "no worker heartbeat in the last 30 s: jobs wait in the queue until a worker starts"),
    ((BUSY,), "1 worker alive (heartbeat within 30 s); celery@box runs job 7f3c"),
    (ConnectionError("gone"), "worker heartbeats could not be read (ConnectionError)"),
])
def test_ready_does_not_depend_on_workers_and_reports_them(ready_client, workers, detail):
    # A solo worker busy training cannot answer a ping: readiness once flapped with it.
    response = ready_client(workers=workers).get("/ready")
    assert response.status_code == 200
    assert response.json()["down"] == [] and response.json()["workers_detail"] == detail


@pytest.mark.parametrize("name", ["mlflow", "storage"])
def test_mlflow_or_storage_down_is_503(ready_client, name):
    body = ready_client(**{name: DOWN}).get("/ready").json()
    assert body["down"] == [name] and body[name]["status"] == "down"


# --- the probes themselves ---------------------------------------------------------------------------------


def test_redis_probe_against_the_test_database(settings, redis_db):
    check = health.check_redis(settings)
    assert check.status == "ok" and check.detail.startswith("PING answered in")


class ConfigRefused:
    """A Redis client whose server refuses CONFIG (as managed services often do) and answers INFO."""

    def __init__(self, aof_enabled: int) -> None:
        self.aof_enabled = aof_enabled

    def config_get(self, name):
        raise redis.ResponseError("unknown command 'CONFIG'")

    def info(self, section):
        return {"aof_enabled": self.aof_enabled}


def test_persistence_falls_back_to_info_when_config_is_refused():
    assert redis_persistence(ConfigRefused(1)) == "aof"
    assert redis_persistence(ConfigRefused(0)) == "unknown"  # INFO does not say whether save points are set


def test_persistence_probe_against_the_test_database(settings, redis_db):
    client = redis.Redis.from_url(settings.redis_url)
    expected = "aof" if client.config_get("appendonly")["appendonly"] == "yes" else (
        "rdb" if client.config_get("save")["save"] else "none")
    assert health.redis_persistence(settings) == expected
    client.close()


def test_redis_probe_down_is_quick_and_names_no_address(settings, caplog):
    url = f"redis://user:hunter2@127.0.0.1:{closed_port()}/15"
    start = time.perf_counter()
    check = health.check_redis(settings.model_copy(update={"redis_url": url}))
    assert time.perf_counter() - start < 3
    assert check.status == "down" and "127.0.0.1" not in check.detail and "redis://" not in check.detail
    assert "hunter2" not in caplog.text and "user:***@127.0.0.1" in caplog.text  # the operator's log has it


def test_mlflow_sqlite_probe_checks_the_folder_and_names_no_path(settings, tmp_path):
    (settings.data_dir / "mlflow").mkdir(parents=True)
    assert health.check_mlflow(settings).status == "ok"  # default: sqlite under data_dir/mlflow
    missing = settings.model_copy(update={"tracking_uri": f"sqlite:///{tmp_path}/nowhere/mlflow.db"})
    check = health.check_mlflow(missing)
    assert check == DependencyCheck(status="down", detail="sqlite store folder does not exist")
    (tmp_path / "file").write_text("x")
    not_a_folder = settings.model_copy(update={"tracking_uri": f"sqlite:///{tmp_path}/file/mlflow.db"})
    assert health.check_mlflow(not_a_folder).status == "down"
    other = settings.model_copy(update={"tracking_uri": "databricks://profile"})
    assert health.check_mlflow(other).status == "skipped"


def test_storage_probe(settings, tmp_path):
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    assert health.check_storage(settings) == DependencyCheck(status="ok", detail="data folder is writable")
    gone = settings.model_copy(update={"data_dir": tmp_path / "gone"})
    assert health.check_storage(gone) == DependencyCheck(status="down", detail="data folder does not exist")


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
    assert check == DependencyCheck(status="ok", detail="GET /health answered 200")
    _Handler.status = 503
    try:
        assert health.check_mlflow(settings.model_copy(update={"tracking_uri": uri})).detail.endswith("answered 503")
    finally:
        _Handler.status = 200
    closed = settings.model_copy(update={"tracking_uri": f"http://127.0.0.1:{closed_port()}"})
    check = health.check_mlflow(closed)
    assert check.status == "down" and "ConnectError" in check.detail and "127.0.0.1" not in check.detail


def test_readiness_schema_has_examples(make_app):
    document = TestClient(make_app(public=(health.router,))).get("/openapi.json").json()
    assert "503" in document["paths"]["/ready"]["get"]["responses"]
    assert document["components"]["schemas"]["Readiness"]["examples"]


def test_worker_heartbeats_are_read_back_and_expire(settings, redis_db):
    prefix = "denoiser:worker:test-"
    heartbeat = Heartbeat(redis_db, "celery@box", ["cpu"], 10.0, prefix=prefix)
    heartbeat.job = "job-1"
    heartbeat.beat()
    [beat] = read_beats(redis_db, prefix)
    assert (beat.hostname, beat.queues, beat.job) == ("celery@box", ["cpu"], "job-1")
    assert 0 < redis_db.ttl(f"{prefix}celery@box") <= 30  # gone after three missed beats
    heartbeat.stop()  # a clean stop removes the key at once
    assert read_beats(redis_db, prefix) == []


def test_a_started_heartbeat_is_listed_at_once_and_gone_after_stop(settings, redis_db):
    prefix = "denoiser:worker:test-"
    heartbeat = Heartbeat(redis_db, "celery@busy", ["cpu"], 10.0, prefix=prefix).start()
    try:
        assert [beat.hostname for beat in read_beats(redis_db, prefix)] == ["celery@busy"]
    finally:
        heartbeat.stop()
    assert read_beats(redis_db, prefix) == []
