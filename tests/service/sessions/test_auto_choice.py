"""Automatic model choice: core.registry.choose_version's rules with known answers, and POST /sessions with
``"model": "auto"`` against registered versions tagged as a fit tags them (the choice and why in the response)."""

from __future__ import annotations

import uuid
from datetime import datetime, timezone

import pytest
from fastapi.testclient import TestClient

from core.registry import ConstraintNotMet, ModelVersionInfo, NoAutoCandidates, choose_version
from service.http.routes import models as models_routes
from service.http.routes import sessions as sessions_routes
from service.sessions.store import get_session_store
from tests.builders import error_of
from tests.service.session_fixtures import MODEL_NAME, make_store, registry_settings, shared_registry

__all__ = ["make_store", "registry_settings"]  # fixtures used by name


def version(name: str, number: int, *, method="wskpn", preset="s", scale=1, flops=None, psnr=None, ms=None,
            params=None) -> ModelVersionInfo:
    metrics = {key: value for key, value in (("validation_psnr", psnr), ("ms_per_frame", ms)) if value is not None}
    tags = {"method": method, "preset": preset, "scale": str(scale)}
    if ms is not None:
        tags["ms_per_frame_resolution"] = "128x128"
    return ModelVersionInfo(name=name, version=str(number), run_id=None, created_at=datetime.now(timezone.utc),
                            method=method, preset=preset, scale=scale, params=params, flops_per_pixel=flops,
                            metrics=metrics, tags=tags, aliases=[], source=None)


VERSIONS = [
    version("fit", 1, preset="xs", flops=1e3, psnr=28.0, ms=4.0),
    version("fit", 2, preset="s", flops=2e3, psnr=30.5, ms=9.0),
    version("fit", 3, preset="m", flops=4e3, psnr=31.0, ms=18.0),
    version("fit", 4, preset="l", flops=8e3, psnr=31.2, ms=35.0),
    version("other", 1, method="jnds", preset="xs", flops=500.0, psnr=33.0, ms=3.0, scale=2),
    version("untimed", 1, preset="xxl", flops=1e5, psnr=40.0),  # no ms_per_frame: not a candidate for budgets
    version("untagged", 1, method=None, flops=1.0, psnr=50.0, ms=0.1),  # not a trained model version
]


def chosen(**constraint) -> tuple[str, str]:
    choice = choose_version(VERSIONS, **constraint)
    return choice.info.name, choice.info.preset


@pytest.mark.parametrize("constraint, expected", [
    ({"min_psnr": 30, "family": "wskpn"}, ("fit", "s")),  # the smallest with the floor
    ({"min_psnr": 30}, ("other", "xs")),  # any family: the jnds one is smaller still
    ({"min_psnr": 35}, ("untimed", "xxl")),  # a PSNR floor alone needs no timing
    ({"min_psnr": 30, "scale": 1}, ("fit", "s")),
    ({"max_ms_per_frame": 20, "family": "wskpn"}, ("fit", "m")),  # the best PSNR within the budget
    ({"max_ms_per_frame": 100, "family": "wskpn"}, ("fit", "l")),
    ({"max_ms_per_frame": 20, "min_psnr": 29, "family": "wskpn"}, ("fit", "s")),  # both: the smallest that passes
])
def test_choices_follow_the_rules(constraint, expected):
    assert chosen(**constraint) == expected


def test_the_reason_names_the_version_the_rule_and_the_measurements():
    by_floor = choose_version(VERSIONS, min_psnr=30, family="wskpn")
    assert by_floor.candidates == 5 and by_floor.constraint == {"min_psnr": 30, "family": "wskpn"}
    assert by_floor.reason == ("fit version 2 (wskpn:s at scale 1, 2000 FLOPs/px): the smallest of the 4 of 5 "
                               "candidate versions of family 'wskpn' with validation PSNR >= 30 dB (30.50 dB)")
    by_budget = choose_version(VERSIONS, max_ms_per_frame=20, family="wskpn")
    assert by_budget.reason == ("fit version 3 (wskpn:m at scale 1, 4000 FLOPs/px): the best validation PSNR "
                                "(31.00 dB) of the 3 of 4 candidate versions of family 'wskpn' within 20 ms per "
                                "frame (18 ms per frame at 128x128)")
    assert by_budget.to_dict()["ms_per_frame_resolution"] == "128x128"


def test_ties_go_to_the_smaller_version():
    twins = [version("a", 1, flops=2e3, psnr=30.0, ms=5.0), version("b", 1, flops=1e3, psnr=30.0, ms=6.0)]
    assert choose_version(twins, max_ms_per_frame=10).info.name == "b"


def test_nothing_to_compare_and_nothing_passing_are_told_apart():
    with pytest.raises(NoAutoCandidates, match="no registered model version of family 'afn' has the tags") as caught:
        choose_version(VERSIONS, min_psnr=20, family="afn")
    assert isinstance(caught.value, KeyError)
    with pytest.raises(ConstraintNotMet) as caught:
        choose_version(VERSIONS, min_psnr=32, max_ms_per_frame=10, family="wskpn")
    assert str(caught.value) == ("none of the 4 candidate versions of family 'wskpn' satisfies max_ms_per_frame 10 "
                                 "and min_psnr 32: the best validation PSNR is 31.20 dB (fit version 4); the "
                                 "fastest takes 4 ms per frame at 128x128 (fit version 1)")
    assert caught.value.details["best_psnr"] == {"ref": "models:/fit/4", "validation_psnr": 31.2}


@pytest.mark.parametrize("constraint, message", [
    ({}, "needs max_ms_per_frame, min_psnr or both"),
    ({"min_psnr": -1}, "min_psnr must be a positive number"),
    ({"max_ms_per_frame": float("nan")}, "max_ms_per_frame must be a positive number"),
    ({"min_psnr": 30, "family": "x' OR 1=1"}, "not a method family name"),
])
def test_malformed_constraints_are_value_errors(constraint, message):
    with pytest.raises(ValueError, match=message):
        choose_version(VERSIONS, **constraint)


# ------------------------------------------------------------------------------------ POST /sessions auto


@pytest.fixture(scope="module")
def family():
    """A family of three registered versions (JNDS xs weights, scale 2) tagged as a fit tags them."""
    from core.tracking import MLflowTracker

    registry = shared_registry()
    name = f"auto-{uuid.uuid4().hex[:8]}"
    family = f"autotest_{uuid.uuid4().hex[:8]}"
    tracker = MLflowTracker(registry.uri, experiment="service-tests")
    tracker.start({"method": family})
    for preset, flops, psnr, ms in (("a", 1000, 25.0, 5.0), ("b", 2000, 30.0, 10.0), ("c", 4000, 32.0, 40.0)):
        tracker.log_model(registry.checkpoints["1"], name, {
            "method": family, "preset": preset, "scale": "2", "params": "16228", "flops_per_pixel": str(flops),
            "validation_psnr": f"{psnr:.4f}", "ms_per_frame": str(ms), "ms_per_frame_resolution": "64x64"})
    tracker.finish("FINISHED")
    return name, family


@pytest.fixture
def client(make_app, make_store):
    store = make_store()
    app = make_app(sessions_routes.router, models_routes.router, tracking_uri=shared_registry().uri)
    app.dependency_overrides[get_session_store] = lambda: store
    return TestClient(app)


@pytest.mark.parametrize("constraint, preset, version", [
    ({"min_psnr": 29}, "b", "2"),
    ({"max_ms_per_frame": 50}, "c", "3"),
    ({"max_ms_per_frame": 50, "min_psnr": 26}, "b", "2"),
])
def test_a_session_with_model_auto_runs_the_chosen_version_and_says_why(client, family, constraint, preset, version):
    name, method = family
    response = client.post("/sessions", json={"model": "auto", "family": method, **constraint})
    assert response.status_code == 201, response.text
    session = response.json()
    assert (session["model"]["name"], session["model"]["version"]) == (name, version)
    assert session["model"]["method"] == "jnds" and session["model"]["scale"] == 2  # what the checkpoint holds
    choice = session["choice"]
    assert (choice["name"], choice["version"], choice["preset"]) == (name, version, preset)
    assert choice["constraint"] == {**constraint, "family": method} and choice["candidates"] == 3
    assert choice["reason"].startswith(f"{name} version {version} ({method}:{preset} at scale 2")
    assert client.get(f"/sessions/{session['id']}").json()["choice"] == choice  # kept with the session


def test_auto_without_a_match_is_404_or_422_with_the_closest_named(client, family):
    _, method = family
    body = error_of(client.post("/sessions", json={"model": "auto", "min_psnr": 40, "family": method}), 422,
                    "constraint_not_met")
    assert "the best validation PSNR is 32.00 dB" in body["message"]
    assert body["details"]["candidates"] == 3
    body = error_of(client.post("/sessions", json={"model": "auto", "min_psnr": 20, "family": "nosuchfamily"}), 404,
                    "no_candidate_model")
    assert "no registered model version of family 'nosuchfamily'" in body["message"]


@pytest.mark.parametrize("body, words", [
    ({"model": "auto"}, "needs max_ms_per_frame, min_psnr or both"),
    ({"model": "auto", "min_psnr": 30, "version": "1"}, "give no version or alias"),
    ({"model": MODEL_NAME, "min_psnr": 30}, "only go with model 'auto'"),
    ({"model": "auto", "min_psnr": 0}, "greater than 0"),
])
def test_malformed_auto_requests_are_422(client, body, words):
    response = client.post("/sessions", json=body)
    assert response.status_code == 422 and words in response.text, response.text
