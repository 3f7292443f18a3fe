"""GET /metrics on the full app: what a Prometheus scrape reads after a session streamed a few frames, jobs and
queues read from Redis at the scrape, a Redis outage, the API key, and route templates as request labels."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from core.job_store import JobStore
from core.settings import get_settings
from service.http.metrics import UNMATCHED_ROUTE, queue_keys
from tests.service.session_fixtures import MODEL_NAME, create, post_frame, stream_frames

FRAMES_ROUTE = "/sessions/{session_id}/frames"


def scrape(client: TestClient, **headers: str) -> dict[tuple[str, tuple], float]:
    """(sample name, sorted labels) -> value of one scrape."""
    response = client.get("/metrics", headers=headers)
    assert response.status_code == 200, response.text
    assert response.headers["content-type"].startswith("text/plain; version=")
    return {(sample.name, tuple(sorted(sample.labels.items()))): sample.value
            for family in text_string_to_metric_families(response.text) for sample in family.samples}


def labels(**values: str) -> tuple:
    return tuple(sorted(values.items()))


@pytest.fixture
def full_client(registry_settings, redis_db):
    """The whole app (its lifespan builds the process's session store on Redis db 15 and the shared registry)."""
    from service.http.app import create_app

    app = create_app()
    with TestClient(app) as client:
        yield app, client


def test_a_scrape_after_a_streamed_session(full_client, redis_db):
    app, client = full_client
    session = create(client)
    frames = stream_frames(3, seed=5)
    for frame in frames:
        assert post_frame(client, session["id"], frame).status_code == 200
    jobs = JobStore(redis_db)
    jobs.create("train", {}, "cpu", "cpu")
    jobs.create("train", {}, "cpu", "cpu")
    running = jobs.create("evaluate", {}, "gpu", "gpu")
    jobs.update(running["id"], state="running")
    redis_db.rpush("cpu", "m1", "m2")
    redis_db.rpush(queue_keys("cpu")[1], "m3")  # a message sent with a priority sits in its own list

    metrics = scrape(client)
    model = labels(model=MODEL_NAME)
    assert metrics[("denoiser_session_frames_total", model)] == len(frames)
    assert metrics[("denoiser_session_step_seconds_count", model)] == len(frames)
    assert metrics[("denoiser_session_step_seconds_sum", model)] > 0
    frames_requests = labels(method="POST", route=FRAMES_ROUTE, status="200")
    assert metrics[("denoiser_http_request_duration_seconds_count", frames_requests)] == len(frames)
    assert metrics[("denoiser_http_request_duration_seconds_count",
                    labels(method="POST", route="/sessions", status="201"))] == 1
    assert metrics[("denoiser_sessions_active", ())] == 1
    assert metrics[("denoiser_jobs", labels(kind="train", state="queued"))] == 2
    assert metrics[("denoiser_jobs", labels(kind="evaluate", state="running"))] == 1
    assert metrics[("denoiser_jobs", labels(kind="evaluate", state="queued"))] == 0
    assert metrics[("denoiser_queue_depth", labels(queue="cpu"))] == 3
    assert metrics[("denoiser_queue_depth", labels(queue="gpu"))] == 0
    assert {key[1]: value for key, value in metrics.items() if key[0] == "denoiser_metrics_source_up"} == {
        labels(source="sessions"): 1, labels(source="jobs"): 1, labels(source="queues"): 1}
    # Every path of the route is one label value: the raw paths (session ids) never appear.
    assert not any(session["id"] in dict(key[1]).get("route", "") for key in metrics)

    assert client.delete(f"/sessions/{session['id']}").status_code == 204
    client.get("/no/such/path")
    after = scrape(client)
    assert after[("denoiser_sessions_active", ())] == 0
    assert after[("denoiser_session_frames_total", model)] == len(frames)  # a counter outlives its session
    assert after[("denoiser_http_request_duration_seconds_count",
                  labels(method="GET", route=UNMATCHED_ROUTE, status="404"))] == 1
    assert after[("denoiser_session_mirror_failures_total", labels(operation="write"))] == 0


def test_a_redis_outage_leaves_out_what_it_cannot_read(full_client):
    app, client = full_client
    dead = get_settings().model_copy(update={"redis_url": "redis://127.0.0.1:1/0"})
    app.dependency_overrides[get_settings] = lambda: dead  # /metrics reads jobs and queues there
    metrics = scrape(client)
    assert metrics[("denoiser_metrics_source_up", labels(source="jobs"))] == 0
    assert metrics[("denoiser_metrics_source_up", labels(source="queues"))] == 0
    assert metrics[("denoiser_metrics_source_up", labels(source="sessions"))] == 1  # the store's own Redis
    assert not any(name in ("denoiser_jobs", "denoiser_queue_depth") for name, _ in metrics)
    assert metrics[("denoiser_sessions_active", ())] == 0


def test_metrics_need_the_api_key_when_one_is_set(registry_settings, redis_db, monkeypatch):
    from service.http.app import create_app

    key = "0123456789abcdef0123456789abcdef"
    monkeypatch.setenv("DENOISER_API_KEY", key)
    get_settings.cache_clear()
    with TestClient(create_app()) as client:
        refused = client.get("/metrics")
        assert refused.status_code == 401 and refused.json()["error"]["code"] == "unauthorized"
        assert scrape(client, **{"X-API-Key": key})[("denoiser_sessions_active", ())] == 0


def test_two_apps_in_one_process_count_apart(make_store):
    from service.http.app import create_app
    from service.sessions.store import get_session_store

    store = make_store()
    apps = [create_app(), create_app()]
    for app in apps:  # no lifespan: both serve this test's store
        app.dependency_overrides[get_session_store] = lambda: store
    first, second = TestClient(apps[0]), TestClient(apps[1])
    for _ in range(3):
        first.get("/health")
    second.get("/health")
    health = ("denoiser_http_request_duration_seconds_count", labels(method="GET", route="/health", status="200"))
    assert scrape(first)[health] == 3
    assert scrape(second)[health] == 1
