"""The whole service end to end: a real API process (uvicorn), a real Celery worker process, real Redis (db 15).

One stack per module (``stack``): the API is ``service.http.app:app`` served by uvicorn on a free port, with an API
key, a temporary data folder and a temporary SQLite MLflow store; the worker is ``celery -A core.celery_app
worker -P solo`` on the same settings. Both are configured by DENOISER_* environment variables only, as deployed.
Changed for the test: the API sends jobs to a queue named for this module, which only this module's worker
consumes (``QUEUE_FOR_DEVICE`` is patched in the API process before it serves), so no other test worker on db 15
can take them, and job recovery re-sends them there too. For speed, the worker imports the training modules
while it starts (``-I``) and this process creates the MLflow store's tables meanwhile (else the first training
pays both, 10-15 s on a busy machine).

Everything lives in Redis db 15 under the service's own key names (job records, session mirrors), removed at the
end. ``tests/service/conftest.py``'s ``redis_db`` fixture flushes db 15, so another test run on the same Redis at
the same time wipes this module's jobs and sessions (the tests then fail with "job ... does not exist").

- ``test_upload_train_register_and_stream``: the path a user takes, through ``client.rest.DenoiserClient``:
  upload a dataset folder, train wskpn:xs for a few steps, find the registered model, open a session by name and
  stream a sequence; the streamed outputs equal ``method.step`` run in this process with the registered checkpoint.
- ``test_a_session_continues_on_a_restarted_api``: the API is killed (SIGKILL) mid-stream and another started on
  the same Redis and data folder; the stream goes on with its history (X-History: continued) and every output
  still equals in-process stepping.
- ``test_a_training_survives_its_worker_being_killed``: the worker is killed (SIGKILL) mid-training, after a
  checkpoint; once the job's lease is gone a new worker's start-up recovery sends it again, and it resumes from
  the checkpoint (attempt 2, "resuming from ... at step N > 0") and succeeds. The lease lives
  ``LEASE_TTL_SECONDS`` (30 s, not configurable); the fast variant removes it by hand right after the kill (what
  30 s would do), the slow one waits for it to expire by itself.

The processes' output goes to ``api-N.log`` and ``worker-N.log`` in the module's temporary folder (pytest keeps
the last runs'); a test that times out waiting prints their ends.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

from model.io.dataset import Dataset, Sequence
from client.rest import DenoiserClient, decode_rgb_exr
from tests.builders import write_sequence, write_tiny_dataset
from tests.service.session_fixtures import assert_same_image, in_process_outputs
from tests.workers.tasks.fixtures import TEST_REDIS_URL, redis_client
from tests.workers.parking import PARKING_ENV
from core.job_store import JobStore

REPOSITORY = Path(__file__).resolve().parents[1]
API_KEY = "e2e-api-key"
MODEL = "e2e-wskpn-xs"
STREAM = "delta"  # the test-split sequence the sessions stream (8 frames, no camera cut)
STREAM_FRAMES = 8
TRAIN = {"method": "wskpn:xs", "scale": 1, "crop": 8, "batch": 2, "frames_per_sample": 2, "warmup_steps": 0,
         "validate_every": 0, "threads": 1}

# The API process: the production app, with this module's queue for every job (see the module notes).
API_SERVER = """
import os, sys, uvicorn
from core.names import QUEUE_FOR_DEVICE
QUEUE_FOR_DEVICE.update(cpu=os.environ["E2E_QUEUE"], gpu=os.environ["E2E_QUEUE"])  # in place: every importer sees it
uvicorn.run("service.http.app:app", host="127.0.0.1", port=int(sys.argv[1]), log_level="info")
"""


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Stack:
    """The API and worker processes of one module, and what the test reads behind their backs (Redis, files)."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.data = root / "data"
        self.tracking_uri = f"sqlite:///{root / 'mlflow' / 'mlflow.db'}"
        (root / "mlflow").mkdir(parents=True)
        self.parking = root / "parking"  # where a test asks a training job to park (tests.workers.parking)
        self.parking.mkdir()
        self.queue = f"test-e2e-{uuid.uuid4().hex[:8]}"
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.redis = redis_client()
        self.jobs = JobStore(self.redis)  # the default prefix, as the API and the worker use
        self.job_ids: list[str] = []
        self.session_ids: list[str] = []
        self.api: subprocess.Popen | None = None
        self.worker: subprocess.Popen | None = None
        self._starts = {"api": 0, "worker": 0}
        self.logs: list[Path] = []
        keep = {name: value for name, value in os.environ.items() if not name.startswith("DENOISER_")}
        self.environment = {
            **keep, "DENOISER_DATA_DIR": str(self.data), "DENOISER_REDIS_URL": TEST_REDIS_URL,
            "DENOISER_TRACKING_URI": self.tracking_uri, "DENOISER_API_KEY": API_KEY,
            "DENOISER_SESSION_THREADS": "1", "E2E_QUEUE": self.queue, "PYTHONPATH": str(REPOSITORY),
            "OMP_NUM_THREADS": "1", "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false",
            PARKING_ENV: str(self.parking)}

    def create_tracking_store(self) -> None:
        """The MLflow store's tables, created while the processes start rather than by the first training (seconds
        of SQLite migrations; MLflowTracker creates them under a file lock, so a process racing this one waits)."""
        from core.tracking import MLflowTracker

        MLflowTracker(self.tracking_uri).client

    # ------------------------------------------------------------------------------------ processes

    def _spawn(self, kind: str, command: list[str]) -> subprocess.Popen:
        self._starts[kind] += 1
        log = self.root / f"{kind}-{self._starts[kind]}.log"
        self.logs.append(log)
        with log.open("wb") as output:
            return subprocess.Popen(command, cwd=REPOSITORY, env=self.environment, stdout=output,
                                    stderr=subprocess.STDOUT)

    def start_api(self) -> None:
        self.api = self._spawn("api", [sys.executable, "-c", API_SERVER, str(self.port)])

    def start_worker(self) -> None:
        self.worker = self._spawn("worker", [
            sys.executable, "-m", "celery", "-A", "core.celery_app", "worker", "-P", "solo", "-Q", self.queue,
            "--concurrency", "1", "-n", f"{self.queue}-{self._starts['worker']}@%h", "--without-gossip",
            "--without-mingle", "--without-heartbeat", "--loglevel", "INFO",
            # Imported while the worker starts rather than by its first job (seconds on a busy machine).
            # tests.workers.parking: the hook that parks a training job where a test asks (PARKING_ENV).
            "-I", "model.training.train,core.tracking,workers.tasks.train,tests.workers.parking"])

    def wait_for_api(self, timeout: float = 90.0) -> None:
        import httpx

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.api.poll() is not None:
                pytest.fail(f"the API exited with status {self.api.returncode}:\n{self.output()}")
            try:
                if httpx.get(f"{self.url}/health", timeout=1).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        pytest.fail(f"the API did not answer /health within {timeout} s:\n{self.output()}")

    @staticmethod
    def kill(process: subprocess.Popen | None) -> None:
        if process is not None and process.poll() is None:
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=30)

    @staticmethod
    def stop(process: subprocess.Popen | None) -> None:
        if process is None or process.poll() is not None:
            return
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()

    def output(self) -> str:
        return "\n".join(f"--- {log.name} ---\n{log.read_text(errors='replace')[-3000:]}"
                         for log in self.logs if log.is_file())

    def client(self) -> DenoiserClient:
        return DenoiserClient(self.url, api_key=API_KEY, timeout=60)

    # --------------------------------------------------------------------------------- waiting

    def wait_for_job(self, job_id: str, predicate: Callable[[dict], bool], timeout: float = 180.0) -> dict:
        """Polls the job record in Redis (not the API, which a test may have killed)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            record = self.jobs.get(job_id)
            if record is not None and predicate(record):
                return record
            if record is not None and record["state"] in ("failed", "cancelled"):
                pytest.fail(f"job {job_id} {record['state']}: {record['error']}\n{self.output()}")
            time.sleep(0.1)
        pytest.fail(f"job {job_id} did not get there within {timeout} s: {self.jobs.get(job_id)}\n{self.output()}")

    def submit(self, client: DenoiserClient, kind: str, params: dict) -> dict:
        job = client.submit_job(kind, params)
        self.job_ids.append(job["id"])
        return job

    def cleanup(self) -> None:
        """This module's keys in db 15: job records and Celery results, session mirrors, the queue and its
        bindings, and the message the killed worker never acknowledged (kombu's ``unacked`` hash)."""
        for job_id in self.job_ids:
            self.jobs.delete(job_id)
            self.redis.delete(f"celery-task-meta-{job_id}")
        for session_id in self.session_ids:
            self.redis.delete(f"denoiser:session:{session_id}")
        self.redis.delete(self.queue, f"_kombu.binding.{self.queue}", f"_kombu.binding_permanent.{self.queue}")
        for tag, message in self.redis.hscan_iter("unacked"):
            if any(job_id in message for job_id in self.job_ids):
                self.redis.hdel("unacked", tag)
                self.redis.zrem("unacked_index", tag)


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    stack = Stack(tmp_path_factory.mktemp("e2e"))
    store = threading.Thread(target=stack.create_tracking_store)
    store.start()
    stack.start_api()
    stack.start_worker()
    try:
        stack.wait_for_api()
        store.join()
        yield stack
    finally:
        stack.stop(stack.api)
        stack.stop(stack.worker)
        stack.cleanup()


@pytest.fixture(scope="module")
def dataset_folder(tmp_path_factory) -> Path:
    """16x16 frames written with SequenceWriter: train alpha (6, a cut at 3) and beta (5), validation gamma (3),
    test delta (8 frames, no cut: the stream)."""
    root = write_tiny_dataset(tmp_path_factory.mktemp("upload") / "e2e-tiny")
    write_sequence(root, STREAM, STREAM_FRAMES, seed=4)
    Dataset(root).add_sequence_dir(STREAM, "test")
    return root


@pytest.fixture(scope="module")
def trained(stack, dataset_folder, tmp_path_factory) -> dict:
    """Upload + train + registration, once for the module: {"dataset", "job", "checkpoint" (as registered)}."""
    from core.tracking import download_registered_checkpoint

    with stack.client() as client:
        dataset = client.upload_dataset(dataset_folder, name="e2e-tiny")
        job = stack.submit(client, "train", {**TRAIN, "dataset": dataset["id"], "steps": 4, "checkpoint_every": 0,
                                             "register_as": MODEL})
        job = client.wait_job(job["id"], timeout=240, max_interval=1.0)
    if job["state"] != "succeeded":
        pytest.fail(f"the training job {job['state']}: {job['error']}\n{stack.output()}")
    checkpoint = download_registered_checkpoint(MODEL, "1", tmp_path_factory.mktemp("registered"),
                                                tracking_uri=stack.tracking_uri)
    return {"dataset": dataset, "job": job, "checkpoint": checkpoint}


def stream_frames(folder: Path) -> list:
    sequence = Sequence(folder / STREAM)
    return [sequence[index] for index in range(len(sequence))]


def test_upload_train_register_and_stream(stack, trained, dataset_folder, tmp_path):
    dataset, job = trained["dataset"], trained["job"]
    assert {(s["name"], s["split"]) for s in dataset["sequences"]} == {
        ("alpha", "train"), ("beta", "train"), ("gamma", "validation"), (STREAM, "test")}
    assert job["state"] == "succeeded", job["error"]
    assert job["attempts"] == 1 and job["progress"]["current"] == job["progress"]["total"] == 4
    assert job["result"]["registered_model"]["name"] == MODEL and job["mlflow_run_id"]

    with stack.client() as client:
        model = client.get_model(MODEL)
        assert [v["version"] for v in model["versions"]] == ["1"] and model["latest_version"] == "1"
        version = model["versions"][0]
        assert (version["method"], version["preset"], version["scale"]) == ("wskpn", "xs", 1)
        assert version["run_id"] == job["mlflow_run_id"]

        session = client.create_session(MODEL)
        stack.session_ids.append(session["id"])
        assert session["model"]["name"] == MODEL and session["model"]["version"] == "1"
        summary = client.stream_sequence(session["id"], dataset_folder / STREAM, tmp_path / "out")

    assert [f.frame_index for f in summary.frames] == list(range(STREAM_FRAMES))
    assert [f.history for f in summary.frames] == ["started"] + ["continued"] * (STREAM_FRAMES - 1)
    expected = in_process_outputs(trained["checkpoint"], stream_frames(dataset_folder))
    for path, image in zip(summary.files, expected, strict=True):
        assert_same_image(decode_rgb_exr(path.read_bytes()), image)


def mirrored_frame(stack: Stack, session_id: str) -> int | None:
    """The next_frame_index the session's Redis mirror holds (what a restarted API continues from)."""
    raw = stack.redis.hget(f"denoiser:session:{session_id}", "meta")
    return json.loads(raw)["next_frame_index"] if raw else None


def test_a_session_continues_on_a_restarted_api(stack, trained, dataset_folder):
    frames = stream_frames(dataset_folder)
    expected = in_process_outputs(trained["checkpoint"], frames)
    half = STREAM_FRAMES // 2
    with stack.client() as client:
        session = client.create_session(MODEL, version=1, on_gap="reject")
        stack.session_ids.append(session["id"])
        for index in range(half):
            output, info = client.send_frame(session["id"], frames[index])
            assert info.history == ("started" if index == 0 else "continued")
            assert_same_image(output, expected[index])
        # A frame's mirror is written just after its response (service.sessions.store); the API is killed once the
        # last one has landed, as any time after that frame's response would leave it.
        deadline = time.monotonic() + 10
        while mirrored_frame(stack, session["id"]) != half and time.monotonic() < deadline:
            time.sleep(0.05)
        assert mirrored_frame(stack, session["id"]) == half

        stack.kill(stack.api)
        stack.start_api()
        stack.wait_for_api()

        assert client.get_session(session["id"])["next_frame_index"] == half
        for index in range(half, STREAM_FRAMES):
            output, info = client.send_frame(session["id"], frames[index])
            assert (info.frame_index, info.history) == (index, "continued")
            assert_same_image(output, expected[index])
        assert client.get_session(session["id"])["frames_processed"] == STREAM_FRAMES


RESUMED = re.compile(r"resuming from \S+ at step (\d+) of (\d+)")


@pytest.mark.parametrize("lease", ["removed", pytest.param("expired", marks=pytest.mark.slow)])
def test_a_training_survives_its_worker_being_killed(stack, trained, lease):
    steps, every = 60, 5
    name = f"{MODEL}-resumed-{lease}"
    # The job's first attempt parks at step 2 * every (its checkpoint written) until its worker is killed: a
    # 60-step job can finish in under a second, so waiting to catch it running would race it.
    (stack.parking / f"{name}.park").write_text(str(2 * every))
    parked = stack.parking / f"{name}.parked"
    with stack.client() as client:
        job = stack.submit(client, "train", {**TRAIN, "dataset": trained["dataset"]["id"], "steps": steps,
                                             "checkpoint_every": every, "register_as": name})
        last = stack.data / "jobs" / job["id"] / "checkpoints" / "last.pt"
        # Progress reaches the record at most every PROGRESS_INTERVAL, so the parked marker says where it is.
        running = stack.wait_for_job(job["id"], lambda r: parked.is_file() and r["state"] == "running")
        assert parked.read_text() == str(2 * every) and last.is_file()
        stack.kill(stack.worker)
        killed_at = stack.jobs.get(job["id"])
        assert killed_at["state"] == "running" and killed_at["progress"]["current"] <= 2 * every, killed_at
        assert running["attempts"] == 1 and running["mlflow_run_id"]

        lease_key = stack.jobs.lease_key(job["id"])
        assert 0 < stack.redis.ttl(lease_key) <= 30
        if lease == "removed":
            stack.redis.delete(lease_key)  # what the TTL does 30 s after the last heartbeat
        else:
            deadline = time.monotonic() + 40
            while stack.redis.exists(lease_key) and time.monotonic() < deadline:
                time.sleep(0.5)
            assert not stack.redis.exists(lease_key)
        stack.start_worker()  # its start-up recovery finds the job running without a lease

        final = client.wait_job(job["id"], timeout=240, max_interval=1.0)
        assert final["state"] == "succeeded", final["error"]
        assert final["attempts"] == 2
        assert final["result"]["steps"] == steps and final["progress"]["current"] == steps
        assert final["result"]["registered_model"]["name"] == name
        assert final["mlflow_run_id"] == running["mlflow_run_id"]  # the resumed execution continued the run
        logs = client.job_logs(job["id"], lines=1000)

    resumed = [RESUMED.search(line) for line in logs if RESUMED.search(line)]
    assert len(resumed) == 1, logs
    step = int(resumed[0].group(1))
    assert step == 2 * every and int(resumed[0].group(2)) == steps  # from the checkpoint it parked at
    assert any("attempt 2 of train job" in line for line in logs)
