"""/jobs over HTTP: parameter checks before queueing, records, cancel, logs, results; the queue is a fake here
(tests/workers/tasks/test_worker.py runs jobs through a real worker)."""

from __future__ import annotations

import io
import zipfile

import numpy as np
import pytest
import redis
from fastapi import FastAPI
from fastapi.testclient import TestClient

from model.training.checkpoint import save_checkpoint
from model.io.dataset import Dataset
from model.io.exr import write_image
from model.methods.registry import build_method
from service.http.errors import install_error_handlers
from service.http.routes import jobs as jobs_routes
from core.settings import get_settings
from core.storage import get_storage
from tests.builders import error_of, write_sequence
from tests.model.training_fixtures import TINY_METHOD
from tests.workers.tasks.datasets import store_dataset
from tests.workers.tasks.fixtures import settings, storage, store  # noqa: F401  (fixtures)
from core.job_store import JobStore
from service.http.dispatch import get_dispatcher


class FakeDispatcher:
    def __init__(self) -> None:
        self.sent: list[tuple[str, str]] = []
        self.revoked: list[str] = []
        self.broken = False

    def send(self, job_id: str, queue: str) -> None:
        if self.broken:
            raise ConnectionError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")
        self.sent.append((job_id, queue))

    def revoke(self, job_id: str) -> None:
        self.revoked.append(job_id)


@pytest.fixture
def dispatcher() -> FakeDispatcher:
    return FakeDispatcher()


@pytest.fixture
def client(settings, storage, store, dispatcher):
    app = FastAPI()
    install_error_handlers(app)
    app.include_router(jobs_routes.router)
    app.dependency_overrides[get_settings] = lambda: settings
    app.dependency_overrides[get_storage] = lambda: storage
    app.dependency_overrides[jobs_routes.job_store_dependency] = lambda: store
    app.dependency_overrides[get_dispatcher] = lambda: dispatcher
    store_dataset(storage)
    with TestClient(app) as client:
        yield client


def evaluate_body(**params) -> dict:
    return {"kind": "evaluate", "params": {"dataset": "tiny", "methods": ["identity"], **params}}


def train_body(**params) -> dict:
    return {"kind": "train", "params": {"dataset": "tiny", "method": TINY_METHOD, "crop": 8, "batch": 2,
                                        "frames_per_sample": 2, **params}}


# -------------------------------------------------------------------------------------------- submit

def test_submit_stores_the_job_queues_it_and_answers_202_with_location(client, store, dispatcher):
    response = client.post("/jobs", json=evaluate_body(frames=2))
    assert response.status_code == 202, response.text
    job = response.json()
    assert response.headers["location"] == f"/jobs/{job['id']}"
    assert job["state"] == "queued" and job["kind"] == "evaluate" and job["queue"] == "cpu"
    assert job["params"]["split"] == "test" and job["params"]["frames"] == 2  # defaults filled in
    assert dispatcher.sent == [(job["id"], "cpu")]
    assert store.get(job["id"])["params"] == job["params"]
    response = client.post("/jobs", json={**train_body(), "device": "gpu"})
    assert response.status_code == 202 and dispatcher.sent[-1] == (response.json()["id"], "gpu")
    response = client.post("/jobs", json=train_body(nodes=2))  # one rank on each of 2 workers
    assert response.status_code == 202 and response.json()["params"]["world_size"] == 2
    assert dispatcher.sent[-1] == (response.json()["id"], "cpu")  # one message: node 0 sends the others' tasks


@pytest.mark.parametrize("body, status, code, words", [
    (evaluate_body(dataset="nope"), 404, "dataset_not_found", "dataset 'nope' does not exist"),
    (evaluate_body(methods=["nope"]), 422, "unknown_method", "unknown method 'nope'"),
    (evaluate_body(methods=["oidn:huge"]), 422, "unknown_preset", "no preset 'huge'"),
    (evaluate_body(scale=2, methods=[TINY_METHOD]), 422, "unsupported_scale", "does not run at scale 2"),
    (evaluate_body(methods=[]), 422, "invalid_request", "methods"),
    (evaluate_body(frames=0), 422, "invalid_request", "frames"),
    (evaluate_body(methods=["jobs/none/checkpoints/last.pt"]), 404, "checkpoint_not_found", "does not exist"),
    (evaluate_body(methods=["/etc/passwd.pt"]), 422, "invalid_checkpoint", "outside the data folder"),
    (evaluate_body(colour="red"), 422, "invalid_request", "colour"),
    ({"kind": "paint", "params": {}}, 422, "invalid_request", "paint"),
    (train_body(method="identity"), 422, "not_trainable", "no trainable parameters"),
    (train_body(method=f"{TINY_METHOD}:huge"), 422, "unknown_preset", "no preset 'huge'"),
    (train_body(steps=0), 422, "invalid_request", "steps"),
    (train_body(lr=-1), 422, "invalid_request", "lr"),
    (train_body(lr="nan"), 422, "invalid_request", "lr"),
    (train_body(batch=3, world_size=2), 422, "invalid_request", "does not split evenly over 2 ranks"),
    (train_body(nodes=0), 422, "invalid_request", "params.nodes: Input should be greater than or equal to 1"),
    (train_body(nodes=2, world_size=3, batch=6), 422, "invalid_request", "does not split evenly over 2 nodes"),
    (train_body(nodes=9, batch=9), 422, "too_many_nodes", "DENOISER_MAX_TRAIN_NODES=8"),
    (train_body(crop=64), 422, "crop_too_large", "smaller than the 64x64 crop"),
    (train_body(epochs=0), 422, "invalid_request", "params.epochs: Input should be greater than or equal to 1"),
    (train_body(steps=10, epochs=2), 422, "invalid_request", "exactly one of steps and epochs"),
    (train_body(spatial_weight=-1.0), 422, "invalid_request", "params.spatial_weight"),
    (train_body(tonemap="sqrt"), 422, "invalid_request", "params.tonemap"),
    (train_body(loss_skip_frames=2), 422, "invalid_request", "some frame must count"),
    # Where a training runs is the service's to choose: the data folder, output folder, device and tracking
    # server are no job parameters.
    (train_body(data="/etc"), 422, "invalid_request", "params.data: Extra inputs are not permitted"),
    (train_body(out="/tmp/x"), 422, "invalid_request", "params.out: Extra inputs are not permitted"),
    (train_body(tracking_uri="sqlite:///x.db"), 422, "invalid_request", "params.tracking_uri"),
    ({"kind": "fit", "params": {"dataset": "tiny", "method": "wskpn", "target": "psnr=30", "lr": -1}},
     422, "invalid_request", "params.lr: Input should be greater than 0"),
    ({"kind": "fit", "params": {"dataset": "tiny", "method": "wskpn", "target": "psnr=30", "world_size": 2}},
     422, "invalid_request", "params.world_size: Extra inputs are not permitted"),
    (train_body(frames_per_sample=9), 422, "sequences_too_short", "9 consecutive frames"),
    (train_body(dataset="../etc"), 422, "invalid_request", "dataset"),
    (train_body(register_as="auto"), 422, "invalid_request", "register_as 'auto' is reserved"),
    ({"kind": "fit", "params": {"dataset": "tiny", "method": "wskpn", "target": "psnr=30", "register_as": "auto"}},
     422, "invalid_request", "register_as 'auto' is reserved"),
    ({"kind": "infer", "params": {"dataset": "tiny", "model": "accumulation", "sequences": ["zeta"]}}, 404,
     "sequence_not_found", "'zeta'"),
    ({"kind": "infer", "params": {"dataset": "tiny", "model": "accumulation", "split": "test",
                                  "sequences": ["delta"]}}, 422, "invalid_request", "not both"),
    ({"kind": "generate", "params": {"dataset": "new", "scenes": ["moon"]}}, 422, "unknown_scene", "'moon'"),
    ({"kind": "generate", "params": {"dataset": "new", "scenes": ["metals"], "size": [8, 0]}}, 422,
     "invalid_request", "size"),
])
def test_bad_parameters_are_refused_before_queueing(client, dispatcher, store, body, status, code, words):
    error = error_of(client.post("/jobs", json=body), status)
    assert (code is None or error["code"] == code) and words in error["message"]
    assert dispatcher.sent == [] and store.ids() == []


def test_generate_refuses_to_overwrite_a_sequence_unless_asked(client, storage):
    write_sequence(storage.dataset("tiny"), "metals_s0", 2)
    Dataset(storage.dataset("tiny")).add_sequence_dir("metals_s0", "train")
    body = {"kind": "generate", "params": {"dataset": "tiny", "scenes": ["metals"]}}
    assert error_of(client.post("/jobs", json=body), 409)["code"] == "sequence_exists"
    body["params"]["overwrite"] = True
    assert client.post("/jobs", json=body).status_code == 202
    body = {"kind": "generate", "params": {"dataset": "brand-new", "scenes": ["all"], "size": 32}}
    job = client.post("/jobs", json=body).json()
    assert len(job["params"]["scenes"]) > 3 and job["params"]["size"] == [32, 32]


DEFAULT_BENCHMARK = ["accumulation", "identity", "oidn:fast", "oidn:balanced", "oidn:high", "oidn-taa:fast",
                     "oidn-taa:balanced", "oidn-taa:high", "svgf"]


def test_benchmark_lists_its_default_methods_in_the_record(client):
    job = client.post("/jobs", json={"kind": "benchmark", "params": {"dataset": "tiny"}}).json()
    assert job["params"]["methods"] == DEFAULT_BENCHMARK and job["params"]["scale"] == 1
    body = {"kind": "benchmark", "params": {"dataset": "tiny", "methods": ["svgf"], "all_presets": True,
                                            "scale": "both"}}
    job = client.post("/jobs", json=body).json()
    assert job["params"]["methods"] == ["svgf", "svgf:rectified"] and job["params"]["scale"] == "both"


def test_a_benchmark_at_both_scales_runs_each_method_where_it_can(client, storage):
    path = storage.job("trained") / "checkpoints" / "last.pt"  # the test-only method runs at scale 1 only
    path.parent.mkdir(parents=True)
    save_checkpoint(path, method=build_method(TINY_METHOD), optimizer=None, scheduler=None, train_config={},
                    step=1, epoch=0.0, rng=None, best_metric=None, extra={})
    body = {"kind": "benchmark", "params": {"dataset": "tiny", "scale": "both", "methods": ["identity"],
                                            "include_learned": ["jobs/trained/checkpoints/last.pt"]}}
    assert client.post("/jobs", json=body).status_code == 202
    body["params"].update(methods=None, include_learned=None, scale=2)
    body["params"]["methods"] = ["jobs/trained/checkpoints/last.pt"]
    assert error_of(client.post("/jobs", json=body), 422)["code"] == "unsupported_scale"
    body["params"]["scale"] = "three"
    assert error_of(client.post("/jobs", json=body), 422)["code"] == "invalid_request"


def test_model_references_go_through_the_registry(client, monkeypatch, tmp_path):
    from core import registry

    def resolve(ref: str):
        if ref == "models:/known/1":
            raise registry.RegistryUnavailable("tracking store at sqlite:///x is unavailable")
        raise registry.UnknownModelError(f"model {ref[len('models:/'):]!r} does not exist")

    monkeypatch.setattr(registry, "resolve_checkpoint", resolve)
    body = {"kind": "infer", "params": {"dataset": "tiny", "model": "models:/ghost@champion"}}
    error = error_of(client.post("/jobs", json=body), 404)
    assert error["code"] == "model_not_found" and "ghost@champion" in error["message"]
    error = error_of(client.post("/jobs", json=evaluate_body(methods=["models:/known/1"])), 503)
    assert error["code"] == "registry_unavailable"


def test_a_trained_checkpoint_is_accepted_by_its_path_in_the_data_folder(client, storage):
    path = storage.job("trained") / "checkpoints" / "last.pt"
    path.parent.mkdir(parents=True)
    save_checkpoint(path, method=build_method(TINY_METHOD), optimizer=None, scheduler=None, train_config={},
                    step=1, epoch=0.0, rng=None, best_metric=None, extra={})
    body = {"kind": "infer", "params": {"dataset": "tiny", "model": "jobs/trained/checkpoints/last.pt"}}
    assert client.post("/jobs", json=body).status_code == 202
    body["params"]["scale"] = 2
    assert error_of(client.post("/jobs", json=body), 422)["code"] == "unsupported_scale"


def test_a_pretrained_model_is_accepted_by_its_name_and_a_damaged_one_is_422(client, tmp_path, monkeypatch):
    import model.deployment.pretrained as pretrained
    from tests.builders import ship_tiny

    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    shipped = ship_tiny(tmp_path / "pretrained", "wskpn-xs-x1")
    assert client.post("/jobs", json=evaluate_body(methods=["wskpn-xs-x1", "oidn:high"])).status_code == 202
    body = {"kind": "infer", "params": {"dataset": "tiny", "model": "wskpn-xs-x1", "scale": 2}}
    assert client.post("/jobs", json=body).status_code == 202  # WSKPN runs at 2x as "+ bicubic"
    shipped.path.write_bytes(b"damaged")
    error = error_of(client.post("/jobs", json=evaluate_body(methods=["wskpn-xs-x1"])), 422)
    assert error["code"] == "invalid_checkpoint" and "damaged or was replaced" in error["message"]


def test_a_broker_that_is_down_answers_503_and_fails_the_record(client, dispatcher, store):
    dispatcher.broken = True
    error = error_of(client.post("/jobs", json=evaluate_body()), 503)
    assert error["code"] == "queue_unavailable" and "Connection refused" in error["message"]
    record = store.get(error["details"]["job_id"])
    assert record["state"] == "failed" and record["error"]["code"] == "queue_unavailable"


# ---------------------------------------------------------------------------------- list, get, cancel

def test_list_filters_pages_and_counts(client):
    ids = [client.post("/jobs", json=body).json()["id"] for body in (evaluate_body(), train_body(), evaluate_body())]
    response = client.get("/jobs", params={"kind": "evaluate"})
    assert [j["id"] for j in response.json()] == [ids[2], ids[0]] and response.headers["x-total-count"] == "2"
    response = client.get("/jobs", params={"limit": 1, "offset": 1})
    assert [j["id"] for j in response.json()] == [ids[1]] and response.headers["x-total-count"] == "3"
    assert client.get("/jobs", params={"state": "running"}).json() == []
    assert error_of(client.get("/jobs", params={"state": "sleeping"}), 422)["code"] == "invalid_request"
    assert error_of(client.get("/jobs", params={"limit": 0}), 422)["code"] == "invalid_request"
    assert client.get(f"/jobs/{ids[1]}").json()["kind"] == "train"
    assert error_of(client.get("/jobs/unknown"), 404)["message"] == "job 'unknown' does not exist"


def test_cancel_a_queued_job_at_once_a_running_one_by_flag_and_never_a_finished_one(client, store, dispatcher):
    queued = client.post("/jobs", json=evaluate_body()).json()["id"]
    response = client.post(f"/jobs/{queued}/cancel")
    assert response.status_code == 202 and response.json()["state"] == "cancelled"
    assert dispatcher.revoked == [queued]
    error = error_of(client.post(f"/jobs/{queued}/cancel"), 409)
    assert error["code"] == "job_finished" and "cancelled" in error["message"]

    running = client.post("/jobs", json=evaluate_body()).json()["id"]
    store.start(running, "worker")
    job = client.post(f"/jobs/{running}/cancel").json()
    assert job["state"] == "running" and job["cancel_requested"] and dispatcher.revoked == [queued]
    assert error_of(client.post("/jobs/unknown/cancel"), 404)["code"] == "not_found"


def test_logs_give_the_last_lines(client, storage):
    job_id = client.post("/jobs", json=evaluate_body()).json()["id"]
    assert client.get(f"/jobs/{job_id}/logs").json() == {"lines": []}
    storage.job(job_id).mkdir(parents=True)
    (storage.job(job_id) / "job.log").write_text("".join(f"line {i}\n" for i in range(500)))
    assert client.get(f"/jobs/{job_id}/logs", params={"lines": 2}).json() == {"lines": ["line 498", "line 499"]}
    assert len(client.get(f"/jobs/{job_id}/logs").json()["lines"]) == 200
    assert error_of(client.get(f"/jobs/{job_id}/logs", params={"lines": 0}), 422)["code"] == "invalid_request"
    (storage.job(job_id) / "checkpoints").mkdir()
    (storage.job(job_id) / "checkpoints" / "ddp.log").write_text("rank 1 says hello\n")
    assert client.get(f"/jobs/{job_id}/logs", params={"source": "ranks"}).json() == {"lines": ["rank 1 says hello"]}
    assert error_of(client.get("/jobs/unknown/logs"), 404)["code"] == "not_found"


def test_artifacts_of_an_evaluation(client, storage):
    job_id = client.post("/jobs", json=evaluate_body()).json()["id"]
    assert error_of(client.get(f"/jobs/{job_id}/artifacts/report.json"), 404)["code"] == "not_found"
    storage.job(job_id).mkdir(parents=True)
    (storage.job(job_id) / "report.json").write_text('{"methods": []}')
    response = client.get(f"/jobs/{job_id}/artifacts/report.json")
    assert response.json() == {"methods": []} and response.headers["content-type"] == "application/json"
    assert error_of(client.get(f"/jobs/{job_id}/artifacts/job.log"), 404)["code"] == "not_found"


def test_an_evaluations_side_by_side_pictures_are_artifacts(client, storage):
    job_id = client.post("/jobs", json=evaluate_body()).json()["id"]
    missing = error_of(client.get(f"/jobs/{job_id}/artifacts/comparison_s010.png"), 404)
    assert "comparison_<sequence>.png by evaluate jobs" in missing["message"]
    storage.job(job_id).mkdir(parents=True)
    (storage.job(job_id) / "comparison_s010.png").write_bytes(b"\x89PNG\r\n\x1a\n")
    (storage.job(job_id) / "comparison_s010.txt").write_text("not a picture")
    response = client.get(f"/jobs/{job_id}/artifacts/comparison_s010.png")
    assert response.content.startswith(b"\x89PNG") and response.headers["content-type"] == "image/png"
    assert error_of(client.get(f"/jobs/{job_id}/artifacts/comparison_s010.txt"), 404)["code"] == "not_found"


def test_a_fit_ladder_is_an_artifact(client, storage):
    job_id = client.post("/jobs", json=evaluate_body()).json()["id"]  # any job: artifacts are files by name
    missing = error_of(client.get(f"/jobs/{job_id}/artifacts/ladder.md"), 404)
    assert "ladder.json and ladder.md by fit jobs" in missing["message"]
    storage.job(job_id).mkdir(parents=True)
    (storage.job(job_id) / "ladder.md").write_text("| preset |\n")
    response = client.get(f"/jobs/{job_id}/artifacts/ladder.md")
    assert response.text == "| preset |\n" and response.headers["content-type"].startswith("text/markdown")


# ------------------------------------------------------------------------------------------- results

def test_results_list_download_and_zip(client, storage, store):
    body = {"kind": "infer", "params": {"dataset": "tiny", "model": "identity"}}
    job_id = client.post("/jobs", json=body).json()["id"]
    assert client.get(f"/jobs/{job_id}/results").json()["sequences"] == []
    assert error_of(client.get(f"/jobs/{job_id}/results.zip"), 404)["code"] == "no_results"
    images = {}
    for sequence in ("delta", "epsilon"):
        (storage.result(job_id) / sequence).mkdir(parents=True)
        for index in range(2):
            images[sequence, index] = np.full((4, 6, 3), index + 0.5, np.float32)
            write_image(storage.result(job_id) / sequence / f"frame_{index:04d}.exr", images[sequence, index])
    store.finish(job_id, "succeeded", result={})

    listing = client.get(f"/jobs/{job_id}/results").json()
    assert listing["complete"] and [s["name"] for s in listing["sequences"]] == ["delta", "epsilon"]
    frame = listing["sequences"][1]["frames"][1]
    assert frame["frame"] == "frame_0001.exr" and frame["frame_index"] == 1
    one = client.get(frame["url"])
    assert one.status_code == 200 and one.headers["content-type"] == "image/x-exr"
    assert client.get(f"/jobs/{job_id}/results/epsilon/1").content == one.content
    assert error_of(client.get(f"/jobs/{job_id}/results/epsilon/7"), 404)["code"] == "not_found"
    assert error_of(client.get(f"/jobs/{job_id}/results/..%2Fetc/1"), 404)["code"] == "not_found"

    archive = zipfile.ZipFile(io.BytesIO(client.get(listing["zip_url"]).content))
    assert sorted(archive.namelist()) == [f"{s}/frame_{i:04d}.exr" for s in ("delta", "epsilon") for i in range(2)]
    assert archive.read("epsilon/frame_0001.exr") == one.content

    other = client.post("/jobs", json=evaluate_body()).json()["id"]
    error = error_of(client.get(f"/jobs/{other}/results"), 404)
    assert error["code"] == "no_results" and "evaluate job" in error["message"]


def test_the_openapi_document_describes_every_job_endpoint(client):
    document = client.get("/openapi.json").json()
    paths = document["paths"]
    assert {"/jobs", "/jobs/{job_id}", "/jobs/{job_id}/cancel", "/jobs/{job_id}/logs", "/jobs/{job_id}/results",
            "/jobs/{job_id}/results.zip", "/jobs/{job_id}/results/{sequence}/{frame}"} <= set(paths)
    schemas = document["components"]["schemas"]
    for name in ("Job", "TrainParams", "EvaluateParams", "GenerateParams", "InferParams", "BenchmarkParams",
                 "FitParams", "StabilityParams"):
        assert schemas[name].get("examples"), name


def test_redis_down_answers_503(settings, storage):
    app = FastAPI()
    install_error_handlers(app)
    app.include_router(jobs_routes.router)
    app.dependency_overrides[get_settings] = lambda: settings
    app.dependency_overrides[get_storage] = lambda: storage
    dead = JobStore(redis.Redis.from_url("redis://127.0.0.1:1/0", socket_connect_timeout=0.2))
    app.dependency_overrides[jobs_routes.job_store_dependency] = lambda: dead
    with TestClient(app) as client:
        error = error_of(client.get("/jobs/abc"), 503)
        assert error["code"] == "redis_unavailable" and "ConnectionError" in error["message"]


# --------------------------------------------------------------------------------------- benchmark chart

def test_chart_png_serves_a_benchmark_jobs_chart_or_404(client, storage):
    job_id = client.post("/jobs", json={"kind": "benchmark", "params": {"dataset": "tiny"}}).json()["id"]
    error = error_of(client.get(f"/jobs/{job_id}/chart.png"), 404)
    assert error["code"] == "no_chart" and "benchmark job, queued" in error["message"]
    storage.job(job_id).mkdir(parents=True)
    png = b"\x89PNG\r\n\x1a\n" + b"chart"
    (storage.job(job_id) / "quality_speed.png").write_bytes(png)
    response = client.get(f"/jobs/{job_id}/chart.png")
    assert response.status_code == 200 and response.content == png
    assert response.headers["content-type"] == "image/png"
    assert client.get(f"/jobs/{job_id}/artifacts/quality_speed.png").content == png  # still there too
    evaluation = client.post("/jobs", json=evaluate_body()).json()["id"]
    assert "evaluate job" in error_of(client.get(f"/jobs/{evaluation}/chart.png"), 404)["message"]
    assert error_of(client.get("/jobs/unknown/chart.png"), 404)["code"] == "not_found"
    assert "/jobs/{job_id}/chart.png" in client.get("/openapi.json").json()["paths"]


def test_a_benchmark_adds_trained_models_to_its_default_methods(client, storage, dispatcher):
    path = storage.job("trained") / "checkpoints" / "last.pt"
    path.parent.mkdir(parents=True)
    save_checkpoint(path, method=build_method(TINY_METHOD), optimizer=None, scheduler=None, train_config={},
                    step=1, epoch=0.0, rng=None, best_metric=None, extra={})
    body = {"kind": "benchmark", "params": {"dataset": "tiny", "include_learned": ["jobs/trained/checkpoints/last.pt"]}}
    job = client.post("/jobs", json=body).json()
    assert job["params"]["methods"] == DEFAULT_BENCHMARK + ["jobs/trained/checkpoints/last.pt"]
    assert job["params"]["include_learned"] is None
    body["params"]["include_learned"] = [TINY_METHOD]  # a registry name has no trained weights
    error = error_of(client.post("/jobs", json=body), 422)
    assert f"include_learned: '{TINY_METHOD}' is not a trained model" in error["message"]


def test_a_benchmark_refuses_untrained_learned_presets(client, dispatcher):
    body = {"kind": "benchmark", "params": {"dataset": "tiny", "methods": ["identity", TINY_METHOD]}}
    error = error_of(client.post("/jobs", json=body), 422)
    assert error["code"] == "untrained_method" and TINY_METHOD in error["message"]
    assert dispatcher.sent == []
    assert client.post("/jobs", json=evaluate_body(methods=[TINY_METHOD])).status_code == 202  # evaluate may


# ------------------------------------------------------------------------------------------- stability

def test_a_stability_job_is_checked_queued_and_serves_its_report(client, storage, dispatcher):
    body = {"kind": "stability", "params": {"dataset": "tiny", "methods": ["identity", "svgf"],
                                            "scenarios": ["clean", "nan_inf_color", "clean"], "frames": 2}}
    response = client.post("/jobs", json=body)
    assert response.status_code == 202, response.text
    job = response.json()
    assert job["params"]["scenarios"] == ["clean", "nan_inf_color"] and job["params"]["vdp"] is False
    assert dispatcher.sent[-1] == (job["id"], "cpu")
    job = client.post("/jobs", json={**body, "params": {"dataset": "tiny", "methods": ["identity"]}}).json()
    assert len(job["params"]["scenarios"]) == 19  # none given: every scenario the dataset allows
    storage.job(job["id"]).mkdir(parents=True)
    (storage.job(job["id"]) / "stability.md").write_text("# Stability\n")
    response = client.get(f"/jobs/{job['id']}/artifacts/stability.md")
    assert response.text == "# Stability\n" and response.headers["content-type"].startswith("text/markdown")


@pytest.mark.parametrize("params, status, code, words", [
    ({"methods": ["identity"], "scenarios": ["earthquake"]}, 422, "invalid_request", "scenarios"),
    ({"methods": ["nope"]}, 422, "unknown_method", "unknown method 'nope'"),
    ({"methods": ["identity"], "base": "zeta"}, 422, "invalid_scenarios", "no sequence 'zeta'"),
    ({"methods": ["identity"], "scenarios": ["moving_light"]}, 422, "no_scenarios", "moving_light"),
    ({"methods": []}, 422, "invalid_request", "methods"),
    ({"dataset": "nope", "methods": ["identity"]}, 404, "dataset_not_found", "'nope'"),
])
def test_a_stability_job_with_bad_parameters_is_refused(client, dispatcher, params, status, code, words):
    body = {"kind": "stability", "params": {"dataset": "tiny", **params}}
    error = error_of(client.post("/jobs", json=body), status)
    assert error["code"] == code and words in error["message"]
    assert dispatcher.sent == []
