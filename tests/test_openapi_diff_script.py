"""scripts/openapi_diff.py: what a change removed from the REST API, on tiny documents with known answers."""

from __future__ import annotations

import copy
import json

from tests.builders import load_script

diff = load_script("openapi_diff")

OLD = {
    "paths": {
        "/jobs": {"get": {"responses": {"200": {}}, "parameters": [{"in": "query", "name": "state"}]},
                  "post": {"responses": {"202": {}, "422": {}}}},
        "/jobs/{id}": {"delete": {"responses": {"204": {}}}},
    },
    "components": {"schemas": {
        "Job": {"properties": {"id": {}, "state": {"enum": ["queued", "running"]}}, "required": ["id"]},
        "Kind": {"enum": ["train", "fit"]},
    }},
}


def test_an_unchanged_or_grown_document_removes_nothing():
    grown = copy.deepcopy(OLD)
    grown["paths"]["/metrics"] = {"get": {"responses": {"200": {}}}}
    grown["components"]["schemas"]["Job"]["properties"]["progress"] = {}
    grown["components"]["schemas"]["Kind"]["enum"].append("stability")
    grown["paths"]["/jobs"]["get"]["responses"]["200"] = {"description": "reworded"}
    assert diff.removals(OLD, OLD) == [] and diff.removals(OLD, grown) == []


def test_every_kind_of_removal_is_named():
    new = copy.deepcopy(OLD)
    del new["paths"]["/jobs/{id}"]
    del new["paths"]["/jobs"]["post"]["responses"]["422"]
    new["paths"]["/jobs"]["get"]["parameters"] = [{"in": "query", "name": "state", "required": True}]
    job = new["components"]["schemas"]["Job"]
    job["properties"]["state"]["enum"] = ["queued"]
    job["required"] = ["id", "state"]
    del new["components"]["schemas"]["Kind"]
    assert sorted(diff.removals(OLD, new)) == sorted([
        "path removed: /jobs/{id}",
        "response removed: POST /jobs -> 422",
        "parameter became required: GET /jobs query state",
        "field became required: Job.state",
        "enum value removed: Job.state 'running'",
        "schema removed: Kind",
    ])
    del new["components"]["schemas"]["Job"]["properties"]["state"]
    assert "field removed: Job.state" in diff.removals(OLD, new)


def test_exit_status_says_whether_anything_was_removed(tmp_path, capsys):
    old, new = tmp_path / "old.json", tmp_path / "new.json"
    old.write_text(json.dumps(OLD))
    smaller = copy.deepcopy(OLD)
    del smaller["paths"]["/jobs"]["get"]
    new.write_text(json.dumps(smaller))
    assert diff.main([str(old), str(old)]) == 0
    assert diff.main([str(old), str(new)]) == 1
    assert "operation removed: GET /jobs" in capsys.readouterr().out
    assert diff.main([str(tmp_path / "missing.json"), str(old)]) == 2


def test_this_checkouts_app_offers_everything_it_documents(tmp_path, monkeypatch):
    monkeypatch.setenv("DENOISER_DATA_DIR", str(tmp_path / "data"))
    spec = diff.load("app")
    assert "/sessions" in spec["paths"] and diff.removals(spec, spec) == []
