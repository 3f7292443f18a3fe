"""A train job on 2 nodes through the REST API and real Celery worker processes (solo pool) on this machine.

Two workers consume a queue of this module's own; the job's execution becomes node 0 on one of them and its node
task node 1 on the other, each with a torchrun of one gloo rank. Once both ranks hold before step K + 1 (the
checkpoint of step K written: ``tests.workers.tasks.holding``), one node's worker is killed with SIGKILL and a
third worker started. Node 1 killed: node 0 replaces it. Node 0 killed: node 1 stops once the job's lease lapses
and recovery runs the job again (attempt 2). Either way the ranks resume from step K and the job ends succeeded
with one MLflow run and the weights of an uninterrupted single-process training.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import torch
from fastapi import FastAPI
from fastapi.testclient import TestClient

from core.jobs.dispatch import CeleryDispatcher
from core.job_store import DEFAULT_PREFIX, JobStore
from core.settings import Settings, get_settings
from core.storage import Storage, get_storage
from core.tracking import MLflowTracker
from model.training.checkpoint import load_checkpoint
from model.training.train import TrainConfig, train
from service.http.dispatch import get_dispatcher
from service.http.errors import install_error_handlers
from service.http.routes import jobs as jobs_routes
from tests.workers.tasks.datasets import store_dataset
from tests.workers.tasks.fixtures import TEST_REDIS_URL, redis_client
from tests.workers.tasks.holding import HOLD_ENV, HOLD_METHOD

pytestmark = pytest.mark.slow

REPOSITORY = Path(__file__).resolve().parents[3]
QUEUE = f"test-nodes-{uuid.uuid4().hex[:8]}"
STEPS, HOLD_AT, FRAMES = 8, 4, 3
TRAINING = {"method": HOLD_METHOD, "steps": STEPS, "crop": 8, "batch": 4, "frames_per_sample": FRAMES, "lr": 0.01,
            "warmup_steps": 0, "validate_every": 0, "checkpoint_every": 2}


class QueueDispatcher(CeleryDispatcher):
    def send(self, job_id: str, queue: str) -> None:
        super().send(job_id, QUEUE)


def _forget_jobs(client) -> None:
    for key in client.scan_iter(f"{DEFAULT_PREFIX}job*"):
        client.delete(key)


def wait_until(condition, timeout: float, what: str, describe=lambda: ""):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.2)
    pytest.fail(f"{what} did not happen in {timeout} s\n{describe()}")


@pytest.mark.parametrize("killed", [1, 0])
def test_a_two_node_job_survives_a_killed_node_by_resuming(tmp_path, killed):
    client = redis_client()
    _forget_jobs(client)
    client.delete(QUEUE, "cpu")
    data, hold = tmp_path / "var", tmp_path / "hold"
    hold.mkdir()
    tracking = f"sqlite:///{tmp_path / 'mlflow.db'}"
    settings = Settings(data_dir=data, redis_url=TEST_REDIS_URL, tracking_uri=tracking)
    storage = Storage(data).ensure()
    store_dataset(storage)
    store = JobStore(client)
    environment = {**os.environ, "DENOISER_DATA_DIR": str(data), "DENOISER_REDIS_URL": TEST_REDIS_URL,
                   "DENOISER_TRACKING_URI": tracking, "DENOISER_NODE_HOST": "127.0.0.1",
                   "DENOISER_RENDEZVOUS_TIMEOUT_SECONDS": "120", "DENOISER_COLLECTIVE_TIMEOUT_SECONDS": "120",
                   "PYTHONPATH": str(REPOSITORY), "OMP_NUM_THREADS": "1", HOLD_ENV: str(hold)}
    workers: dict[str, subprocess.Popen] = {}

    def start_worker(name: str) -> None:
        # The records name the queue of their device (cpu), where recovery sends a job again.
        command = [sys.executable, "-m", "celery", "-A", "core.celery_app", "worker", "-P", "solo",
                   "-Q", f"{QUEUE},cpu", "--concurrency", "1", "-n", f"{name}-{QUEUE}@%h", "--without-gossip", "--without-mingle",
                   "--without-heartbeat", "--loglevel", "INFO", "-I", "tests.workers.tasks.holding"]
        with (tmp_path / f"{name}.log").open("wb") as log:
            workers[name] = subprocess.Popen(command, cwd=REPOSITORY, env=environment, stdout=log,
                                             stderr=subprocess.STDOUT)

    def logs() -> str:
        job_logs = [p.read_text(errors="replace")[-3000:] for p in data.glob("jobs/*/job.log")]
        worker_logs = [f"--- {p.name}\n" + p.read_text(errors="replace")[-3000:] for p in tmp_path.glob("*.log")]
        return "\n".join(job_logs + worker_logs)

    (hold / "hold").write_text(f"{HOLD_AT} {FRAMES}")
    start_worker("a")
    start_worker("b")
    app = FastAPI()
    install_error_handlers(app)
    app.include_router(jobs_routes.router)
    app.dependency_overrides[get_settings] = lambda: settings
    app.dependency_overrides[get_storage] = lambda: storage
    from celery import Celery

    celery = Celery("nodes-tests", broker=TEST_REDIS_URL, backend=TEST_REDIS_URL)
    app.dependency_overrides[get_dispatcher] = lambda: QueueDispatcher(celery)
    try:
        with TestClient(app) as api:
            params = {"dataset": "tiny", **TRAINING, "nodes": 2, "register_as": "tiny-hold-nodes"}
            response = api.post("/jobs", json={"kind": "train", "params": params})
            assert response.status_code == 202, response.text
            job_id = response.json()["id"]
            assert response.json()["params"]["world_size"] == 2

            wait_until(lambda: len(list(hold.glob("held-*"))) == 2, 240, "both ranks holding", logs)
            owner = store.lease_holder(job_id)  # host:pid:token of node 0's execution
            node_zero = int(owner.split(":")[1])
            (victim,) = [name for name, process in workers.items() if (process.pid == node_zero) == (killed == 0)]
            assert last_step(storage, job_id) == HOLD_AT
            workers[victim].send_signal(signal.SIGKILL)
            workers[victim].wait(timeout=10)
            (hold / "hold").unlink()
            start_worker("c")

            record = wait_until(lambda: _finished(store.get(job_id)), 400, "the job's end", logs)
            assert record["state"] == "succeeded", f"{record['error']}\n{logs()}"
            result = record["result"]
            assert result["steps"] == STEPS and result["resumed_from_step"] == HOLD_AT
            job_log = (storage.job(job_id) / "job.log").read_text()
            if killed == 1:
                assert record["attempts"] == 1
                assert "node 1 was lost" in job_log and "sending a replacement (1 of 3)" in job_log
            else:
                # Node 1's torchrun fails on its own once the rendezvous host is gone, or its task stops when the
                # lease lapses; either way recovery runs the job again.
                assert record["attempts"] == 2 and "attempt 2 of train job" in job_log

            # One MLflow run: created by node 0, continued by rank 0 before and after the resume.
            tracker = MLflowTracker(tracking, "denoiser")
            runs = tracker.client.search_runs([tracker.client.get_experiment_by_name("denoiser").experiment_id])
            assert [run.info.run_id for run in runs] == [record["mlflow_run_id"]] == [result["run_id"]]
            assert runs[0].info.status == "FINISHED" and result["registered_model"]["name"] == "tiny-hold-nodes"
    finally:
        for process in workers.values():
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for process in workers.values():
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        celery.close()
        _forget_jobs(client)
        client.delete(QUEUE, "cpu")

    # The resumed job ends with the weights of one uninterrupted process on the same global batch (4), to float32
    # rounding of the ranks' gradient allreduce (see test_train_nodes).
    single = train(TrainConfig(**TRAINING, data=str(storage.dataset("tiny")), out=str(tmp_path / "one"),
                               device="cpu"))
    one, two = load_checkpoint(single["checkpoint"]), load_checkpoint(storage.job(job_id) / "checkpoints" / "last.pt")
    assert two["step"] == STEPS
    for name, tensor in one["model"].items():
        torch.testing.assert_close(two["model"][name], tensor, rtol=1e-5, atol=1e-6)


def last_step(storage: Storage, job_id: str) -> int:
    return int(load_checkpoint(storage.job(job_id) / "checkpoints" / "last.pt")["step"])


def _finished(record: dict | None) -> dict | None:
    return record if record and record["state"] in ("succeeded", "failed", "cancelled") else None
