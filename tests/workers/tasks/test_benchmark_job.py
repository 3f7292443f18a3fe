"""A benchmark job at both scales: each method where it runs, the benchmark table and charts `denoiser benchmark`
writes, one result per scale."""

from __future__ import annotations

import json

import pytest

from core.jobs.kinds import JOB_PARAMS, check
from model.methods.registry import build_method
from model.training.checkpoint import save_checkpoint
from tests.model.training_fixtures import TINY_METHOD
from tests.workers.tasks.datasets import store_dataset
from workers.tasks.jobs import execute


@pytest.fixture
def dataset(storage):
    return store_dataset(storage)


def test_a_benchmark_at_both_scales_runs_each_method_where_it_can(store, storage, settings, dataset):
    checkpoint = storage.job("trained") / "checkpoints" / "last.pt"  # the test-only method runs at scale 1 only
    save_checkpoint(checkpoint, method=build_method(TINY_METHOD), train_config={}, step=1)
    params = JOB_PARAMS["benchmark"].model_validate({
        "dataset": "tiny", "scale": "both", "methods": ["identity"], "frames": 3, "vdp": False,
        "oidn_timing": False, "track": False, "include_learned": ["jobs/trained/checkpoints/last.pt"]})
    job_id = store.create("benchmark", check("benchmark", params, storage, settings), "cpu", "cpu")["id"]
    execute(job_id, store, storage, settings)
    record = store.require(job_id)
    assert record["state"] == "succeeded", record["error"]
    result = record["result"]
    assert result["scales"] == [1, 2] and [run["scale"] for run in result["runs"]] == [1, 2]
    assert [[m["source"] for m in run["methods"]] for run in result["runs"]] == [
        ["identity", "jobs/trained/checkpoints/last.pt"], ["identity"]]
    assert result["skipped"] == [{"method": "jobs/trained/checkpoints/last.pt", "scale": 2,
                                  "reason": "jobs/trained/checkpoints/last.pt does not run at scale 2"}]
    folder = storage.job(job_id)
    document = json.loads((folder / "benchmark.json").read_text())
    assert document["scales"] == [1, 2] and len(document["rows"]) == 3
    assert (folder / "quality_speed.png").read_bytes()[:4] == b"\x89PNG"
    assert not (folder / "report.json").exists()  # one report per scale: they are in benchmark.json
    assert set(result["artifacts"]) == {"benchmark.json", "benchmark.md", "quality_speed.png", "quality_cost.png"}
    assert "| identity | x2 |" in result["table"]
