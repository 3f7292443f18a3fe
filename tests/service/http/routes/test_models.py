"""/models over HTTP: registered models, versions with tags and metrics, aliases, and 4xx for unknown ones."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.http.routes import models as models_routes
from tests.builders import error_message
from tests.service.session_fixtures import MODEL_NAME, register_model, shared_registry, unique_name


@pytest.fixture
def client(make_app) -> TestClient:
    return TestClient(make_app(models_routes.router, tracking_uri=shared_registry().uri))


def test_models_are_listed_with_latest_version_and_aliases(client):
    models = {m["name"]: m for m in client.get("/models").json()}
    assert models[MODEL_NAME] == {"name": MODEL_NAME, "description": None, "latest_version": "2",
                                  "aliases": {"champion": "1"}}


def test_a_model_with_its_versions(client):
    detail = client.get(f"/models/{MODEL_NAME}").json()
    assert detail["latest_version"] == "2" and [v["version"] for v in detail["versions"]] == ["1", "2"]
    first, second = detail["versions"]
    assert {key: first[key] for key in ("method", "preset", "scale", "flops_per_pixel", "aliases", "ref")} == {
        "method": "jnds", "preset": "xs", "scale": 2, "flops_per_pixel": 13416.0, "aliases": ["champion"],
        "ref": f"models:/{MODEL_NAME}/1"}
    assert first["params"] > 10_000 and first["run_id"] and first["created_at"]
    assert first["metrics"] == {"validation_psnr": 21.5}
    assert second["metrics"] == {"ms_per_frame": 3.25, "flip": 0.2}
    assert client.get(f"/models/{MODEL_NAME}/versions/2").json() == second


def test_unknown_models_and_versions(client):
    assert "model 'nope' does not exist" in error_message(client.get("/models/nope"), 404, "not_found")
    assert "version 9 of model" in error_message(client.get(f"/models/{MODEL_NAME}/versions/9"), 404, "not_found")
    assert "not a positive integer" in error_message(client.get(f"/models/{MODEL_NAME}/versions/x"), 422,
                                                "invalid_request")
    assert "has no alias 'gold'" in error_message(client.get(f"/models/{MODEL_NAME}/aliases/gold"), 404, "not_found")


def test_aliases_are_set_read_moved_and_deleted(client):
    name = unique_name("alias-api")
    register_model(name, versions=2)
    response = client.put(f"/models/{name}/aliases/staging", json={"version": "1"})
    assert response.status_code == 200, response.text
    assert response.json()["version"] == "1" and response.json()["model_version"]["aliases"] == ["staging"]
    assert client.put(f"/models/{name}/aliases/staging", json={"version": "2"}).json()["version"] == "2"
    assert client.get(f"/models/{name}/aliases/staging").json()["model_version"]["version"] == "2"
    assert client.get(f"/models/{name}").json()["aliases"] == {"staging": "2"}

    assert client.delete(f"/models/{name}/aliases/staging").status_code == 204
    error_message(client.get(f"/models/{name}/aliases/staging"), 404, "not_found")
    error_message(client.delete(f"/models/{name}/aliases/staging"), 404, "not_found")
    error_message(client.put(f"/models/{name}/aliases/staging", json={"version": "5"}), 404, "not_found")
    error_message(client.put("/models/nope/aliases/staging", json={"version": "1"}), 404, "not_found")
    assert "reserved" in error_message(client.put(f"/models/{name}/aliases/latest", json={"version": "1"}), 422,
                                  "invalid_request")
    error_message(client.put(f"/models/{name}/aliases/staging", json={"version": "two"}), 422, "invalid_request")
    error_message(client.put(f"/models/{name}/aliases/staging", json={}), 422, "invalid_request")


def test_versions_and_models_are_deleted_with_their_aliases_and_cached_checkpoints(client, settings):
    from core.registry import registry_for

    name = unique_name("delete-api")
    register_model(name, versions=2)
    assert client.put(f"/models/{name}/aliases/champion", json={"version": "2"}).status_code == 200
    registry = registry_for(shared_registry().uri, settings.data_dir)
    cached = registry.checkpoint(name, "2")
    assert cached.is_file()

    assert client.delete(f"/models/{name}/versions/2").status_code == 204
    assert not cached.exists()
    detail = client.get(f"/models/{name}").json()
    assert [v["version"] for v in detail["versions"]] == ["1"] and detail["aliases"] == {}
    assert "version 2 of model" in error_message(client.delete(f"/models/{name}/versions/2"), 404, "not_found")
    assert "not a positive integer" in error_message(client.delete(f"/models/{name}/versions/x"), 422, "invalid_request")

    assert client.delete(f"/models/{name}").status_code == 204
    assert f"model '{name}' does not exist" in error_message(client.get(f"/models/{name}"), 404, "not_found")
    assert f"model '{name}' does not exist" in error_message(client.delete(f"/models/{name}"), 404, "not_found")
