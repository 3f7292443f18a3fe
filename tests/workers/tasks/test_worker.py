"""Jobs end to end: the API (in this process) and a real Celery worker process (solo pool) over Redis db 15.

The worker consumes a queue named for this test module only, and the jobs are tiny (16x16 synthetic frames).
Before it starts, a job is left behind as a killed worker would leave it (running, no lease, no message): the
worker's start-up recovery must run it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import pytest
from celery import Celery
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.http.errors import install_error_handlers
from service.http.routes import jobs as jobs_routes
from core.settings import Settings, get_settings
from core.storage import Storage, get_storage
from tests.model.training_fixtures import TINY_METHOD
from tests.workers.tasks.datasets import store_dataset
from tests.workers.tasks.fixtures import TEST_REDIS_URL, redis_client
from core.job_store import DEFAULT_PREFIX, JobStore
from service.http.dispatch import get_dispatcher
from core.jobs.dispatch import CeleryDispatcher

REPOSITORY = Path(__file__).resolve().parents[3]
QUEUE = f"test-jobs-{uuid.uuid4().hex[:8]}"
EVALUATE = {"dataset": "tiny", "split": "test", "scale": 1, "methods": ["identity", "accumulation"], "frames": None,
            "vdp": False, "oidn_timing": False, "threads": 1, "track": False}


class ModuleQueueDispatcher(CeleryDispatcher):
    """Sends every job to this module's queue, which only the test worker consumes."""

    def send(self, job_id: str, queue: str) -> None:
        super().send(job_id, QUEUE)


@dataclass
class Worker:
    process: subprocess.Popen
    log: Path
    store: JobStore
    settings: Settings
    storage: Storage
    orphan: str

    def output(self) -> str:
        return self.log.read_text(errors="replace")[-4000:]

    def wait_for(self, job_id: str, predicate, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            record = self.store.get(job_id)
            if predicate(record):
                return record
            if self.process.poll() is not None:
                pytest.fail(f"the worker exited with status {self.process.returncode}:\n{self.output()}")
            time.sleep(0.1)
        pytest.fail(f"job {job_id} did not get there in {timeout} s: {self.store.get(job_id)}\n{self.output()}")


def _forget_test_jobs(client) -> None:
    # Db 15 is the tests' database: job records (default prefix) of earlier runs would be "recovered" otherwise.
    for key in client.scan_iter(f"{DEFAULT_PREFIX}job*"):
        client.delete(key)


@pytest.fixture(scope="module")
def worker(tmp_path_factory):
    client = redis_client()
    _forget_test_jobs(client)
    data = tmp_path_factory.mktemp("worker") / "var"
    settings = Settings(data_dir=data, redis_url=TEST_REDIS_URL)
    storage = Storage(data).ensure()
    store_dataset(storage)
    store = JobStore(client)
    orphan = store.create("evaluate", EVALUATE, "cpu", QUEUE)["id"]
    store.update(orphan, state="running", attempts=1, started_at="2026-01-01T00:00:00+00:00")
    log = data.parent / "worker.log"
    environment = {**os.environ, "DENOISER_DATA_DIR": str(data), "DENOISER_REDIS_URL": TEST_REDIS_URL,
                   "PYTHONPATH": str(REPOSITORY), "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "celery", "-A", "core.celery_app", "worker", "-P", "solo", "-Q", QUEUE,
               "--concurrency", "1", "-n", f"{QUEUE}@%h", "--without-gossip", "--without-mingle",
               "--without-heartbeat", "--loglevel", "INFO", "-I", "tests.model.training_fixtures"]
    with log.open("wb") as output:
        process = subprocess.Popen(command, cwd=REPOSITORY, env=environment, stdout=output, stderr=subprocess.STDOUT)
    try:
        yield Worker(process, log, store, settings, storage, orphan)
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        _forget_test_jobs(client)
        client.delete(QUEUE)


@pytest.fixture(scope="module")
def celery_client():
    app = Celery("jobs-tests", broker=TEST_REDIS_URL, backend=TEST_REDIS_URL)
    yield app
    app.close()


@pytest.fixture
def api(worker, celery_client):
    app = FastAPI()
    install_error_handlers(app)
    app.include_router(jobs_routes.router)
    app.dependency_overrides[get_settings] = lambda: worker.settings
    app.dependency_overrides[get_storage] = lambda: worker.storage
    app.dependency_overrides[get_dispatcher] = lambda: ModuleQueueDispatcher(celery_client)
    with TestClient(app) as client:
        yield client


def finished(record: dict) -> bool:
    return record["state"] in ("succeeded", "failed", "cancelled")


def test_a_job_orphaned_by_a_killed_worker_is_run_when_a_worker_starts(worker):
    record = worker.wait_for(worker.orphan, finished)
    assert record["state"] == "succeeded", record["error"]
    assert record["attempts"] == 2 and record["started_at"] == "2026-01-01T00:00:00+00:00"
    assert [m["source"] for m in record["result"]["methods"]] == ["identity", "accumulation"]


def test_an_evaluation_submitted_over_http_runs_on_the_worker(worker, api, celery_client):
    response = api.post("/jobs", json={"kind": "evaluate", "params": EVALUATE})
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    worker.wait_for(job_id, finished)
    job = api.get(response.headers["location"]).json()
    assert job["state"] == "succeeded", job["error"]
    assert job["progress"]["current"] == job["progress"]["total"] == 4 and job["attempts"] == 1
    assert job["result"]["methods"][1]["label"] == "accumulation"
    lines = api.get(f"/jobs/{job_id}/logs", params={"lines": 50}).json()["lines"]
    assert any("attempt 1 of evaluate job" in line for line in lines) and "succeeded" in lines[-1]
    assert "| accumulation |" in api.get(f"/jobs/{job_id}/artifacts/report.md").text
    # Celery's own record of the task, under the job's id.
    assert celery_client.AsyncResult(job_id).state == "SUCCESS"


def test_a_running_training_is_cancelled_over_http(worker, api):
    params = {"dataset": "tiny", "method": TINY_METHOD, "steps": 1_000_000, "crop": 8, "batch": 2,
              "frames_per_sample": 2, "warmup_steps": 0, "validate_every": 0, "checkpoint_every": 0, "track": False}
    job_id = api.post("/jobs", json={"kind": "train", "params": params}).json()["id"]
    record = worker.wait_for(job_id, lambda r: r["state"] == "running" and r["progress"]["current"] > 0)
    assert record["progress"]["total"] == 1_000_000 and record["progress"]["eta_seconds"] is not None
    response = api.post(f"/jobs/{job_id}/cancel")
    assert response.status_code == 202 and response.json()["cancel_requested"]
    started = time.monotonic()
    record = worker.wait_for(job_id, finished, timeout=20)
    assert record["state"] == "cancelled" and record["error"] is None
    assert time.monotonic() - started < 10
    assert api.post(f"/jobs/{job_id}/cancel").status_code == 409
