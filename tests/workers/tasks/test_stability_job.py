"""The stability job: its check (from the manifests) and a run on the tiny stored dataset, with and without MLflow."""

from __future__ import annotations

import json

import pytest

from core.errors import Invalid, NotFound
from core.jobs.kinds import JOB_PARAMS, check
from model.names import STABILITY_SCENARIOS
from tests.model.training_fixtures import TINY_METHOD
from tests.workers.tasks.datasets import store_dataset
from workers.tasks.jobs import execute


@pytest.fixture
def dataset(storage):
    return store_dataset(storage)


def submit(store, storage, settings, **params) -> str:
    checked = check("stability", JOB_PARAMS["stability"].model_validate({"dataset": "tiny", **params}), storage,
                    settings)
    return store.create("stability", checked, "cpu", "cpu")["id"]


def test_the_check_fills_the_scenarios_and_refuses_what_cannot_run(storage, settings, dataset):
    params = JOB_PARAMS["stability"]
    checked = check("stability", params(dataset="tiny", methods=["identity"]), storage, settings)
    assert checked["scenarios"] == list(STABILITY_SCENARIOS) and checked["seed"] == 0 and checked["track"]
    with pytest.raises(Invalid, match="no sequence 'zeta'"):
        check("stability", params(dataset="tiny", methods=["identity"], base="zeta"), storage, settings)
    with pytest.raises(Invalid, match="moving_object: no sequence of scene 'moving_object'"):
        check("stability", params(dataset="tiny", methods=["identity"], scenarios=["moving_object"]), storage,
              settings)
    with pytest.raises(Invalid, match="does not run at scale 2"):
        check("stability", params(dataset="tiny", methods=[TINY_METHOD], scale=2), storage, settings)
    with pytest.raises(NotFound, match="dataset 'gone'"):
        check("stability", params(dataset="gone", methods=["identity"]), storage, settings)


def test_a_stability_job_writes_the_suites_report_into_its_folder(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, methods=["identity", "accumulation"], frames=3, track=False,
                    scenarios=["clean", "nan_inf_color", "zero_motion"])
    reports = []
    execute(job_id, store, storage, settings, sink=reports.append)
    record = store.require(job_id)
    assert record["state"] == "succeeded", record["error"]
    result = record["result"]
    assert result["scenarios"] == ["clean", "nan_inf_color", "zero_motion"] and result["dataset"] == "tiny"
    assert [m["source"] for m in result["methods"]] == ["identity", "accumulation"]
    assert all(m["failures"] == [] for m in result["methods"])
    assert result["ghosting"]["least"] == "accumulation"  # the one temporal method
    folder = storage.job(job_id)
    report = json.loads((folder / "stability.json").read_text())
    assert report["data"] == "tiny" and [s["frames"] for s in report["scenarios"]] == [3, 3, 3]
    assert "## Ghosting" in (folder / "stability.md").read_text()
    assert {"stability.json", "stability.md", "psnr_curves.png", "psnr_drop.png"} <= set(result["artifacts"])
    assert result["artifacts"]["stability.md"] == f"/jobs/{job_id}/artifacts/stability.md"
    # Progress: 2 methods x 3 scenarios, in the fixed shape.
    assert record["progress"]["current"] == record["progress"]["total"] == 6
    assert reports and all(set(r) == {"current", "total", "message", "eta_seconds"} for r in reports)
    assert record["mlflow_run_id"] is None


def test_a_tracked_stability_job_logs_its_scores_to_mlflow(store, storage, settings, dataset):
    from mlflow.tracking import MlflowClient

    job_id = submit(store, storage, settings, methods=["accumulation"], frames=2, scenarios=["clean"])
    execute(job_id, store, storage, settings)
    record = store.require(job_id)
    assert record["state"] == "succeeded", record["error"]
    run = MlflowClient(settings.resolved_tracking_uri()).get_run(record["mlflow_run_id"])
    assert run.data.params["scenarios"] == "clean" and "accumulation/median_gain_db" in run.data.metrics
    assert run.info.status == "FINISHED"
