"""The ``fit`` job run in this process by workers.tasks.jobs.execute (Redis db 15, a tmp data folder, no MLflow):
checked before queueing, the ladder in the result and the job folder, an unmet target failing the job."""

from __future__ import annotations

import json

import pytest

from core.errors import DomainError, Invalid, NotFound
from core.jobs.kinds import JOB_PARAMS
from tests.model.training_fixtures import TINY_METHOD
from tests.workers.tasks.datasets import store_dataset
from workers.tasks.jobs import execute
from core.jobs.kinds import check


@pytest.fixture
def dataset(storage):
    return store_dataset(storage)


def fit_params(**changes) -> dict:
    return {"dataset": "tiny", "method": TINY_METHOD, "presets": ["default", "dropout"], "target": "psnr=1",
            "steps": 2, "crop": 8, "batch": 2, "frames_per_sample": 2, "warmup_steps": 0, "time_at": [16, 16],
            "timing_frames": 2, "track": False, **changes}


def submit(store, storage, settings, **params) -> str:
    checked = check("fit", JOB_PARAMS["fit"].model_validate(params), storage, settings)
    return store.create("fit", checked, "cpu", "cpu")["id"]


def test_a_fit_job_trains_what_the_target_needs_and_reports_the_ladder(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, **fit_params())
    reports: list[dict] = []
    execute(job_id, store, storage, settings, sink=reports.append)
    record = store.require(job_id)
    assert record["state"] == "succeeded", record["error"]
    result = record["result"]
    assert result["chosen"] == "default" and result["met"] and result["target"] == "psnr=1"
    assert [(r["preset"], r["status"]) for r in result["ladder"]] == [("default", "trained"), ("dropout", "skipped")]
    assert result["ladder"][0]["checkpoint"].startswith(f"jobs/{job_id}/fit/default-")
    assert result["registered"] is None and result["timing"]["resolution"] == "16x16"
    folder = storage.job(job_id)
    assert json.loads((folder / "ladder.json").read_text())["chosen"] == "default"
    assert "| **default** (chosen) |" in (folder / "ladder.md").read_text()
    assert result["artifacts"] == {name: f"/jobs/{job_id}/artifacts/{name}" for name in ("ladder.json", "ladder.md")}
    assert reports[-1]["current"] == reports[-1]["total"] and record["progress"]["current"] == 2


def test_a_target_no_preset_meets_fails_the_job_with_the_closest(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, **fit_params(target="ms=0.000001"))
    execute(job_id, store, storage, settings)
    record = store.require(job_id)
    assert record["state"] == "failed" and record["error"]["code"] == "target_not_met"
    assert record["error"]["message"].startswith("no preset runs within 1e-06 ms per frame at 16x16; the fastest")
    assert (storage.job(job_id) / "ladder.json").is_file()
    assert f"(ladder: GET /jobs/{job_id}/artifacts/ladder.md or ladder.json" in record["error"]["message"]


@pytest.mark.parametrize("changes, error_type, code, words", [
    ({"target": "fast"}, Invalid, "invalid_target", "is not one of psnr=DB"),
    ({"method": "identity"}, Invalid, "not_trainable", "only learned methods train"),
    ({"method": "nope"}, Invalid, "unknown_method", "unknown method 'nope'"),
    ({"presets": ["huge"]}, Invalid, "unknown_preset", "no preset 'huge'"),
    ({"dataset": "missing"}, NotFound, "dataset_not_found", "'missing' does not exist"),
    ({"validation_split": "train", "train_split": "test", "crop": 32}, Invalid, "crop_too_large", "32x32 crop"),
    ({"alias": "v3"}, Invalid, "invalid_params", "reserved by MLflow"),
    ({"alias": "LATEST"}, Invalid, "invalid_params", "reserved by MLflow"),  # MLflow ignores the case
])
def test_bad_fits_are_refused_before_queueing(store, storage, settings, dataset, changes, error_type, code, words):
    with pytest.raises(DomainError) as caught:
        submit(store, storage, settings, **fit_params(**changes))
    assert (type(caught.value), caught.value.code) == (error_type, code) and words in caught.value.message
