"""The identifier rules the OpenAPI document states are the ones the server's checks apply (service/http/identifiers)."""

from __future__ import annotations

import re

import pytest

from core.registry import MAX_VERSION, checked_version
from core.storage import checked_id
from service.http.app import create_app
from service.sessions.store import SESSION_ID

SCHEMA = create_app().openapi()


def documented(path: str, method: str, name: str) -> dict:
    parameter, = [p for p in SCHEMA["paths"][path][method]["parameters"] if p["name"] == name]
    return parameter["schema"]


def allows(schema: dict, value: str) -> bool:
    # fullmatch: in a JSON schema (ECMA regex), "$" does not match before a final newline as Python's does
    return re.fullmatch(schema["pattern"], value) is not None and len(value) <= schema.get("maxLength", len(value))


IDS = ["rooms", "a", "A.b_c-d", "kitchen_7", "a.", "a.-b", "a..b", ".hidden", "-x", "_x", "a/b", "a:b", "a b", "",
       "rooms\n", "é", "a" * 128, "a" * 129, "1.2.3", "x..", "a.b."]


@pytest.mark.parametrize("value", IDS)
@pytest.mark.parametrize("path,method,name", [("/datasets/{dataset_id}", "get", "dataset_id"),
                                              ("/models/{name}", "get", "name"),
                                              ("/datasets/{dataset_id}/sequences/{sequence}/commit", "post",
                                               "sequence")])
def test_a_documented_id_is_what_checked_id_accepts(value, path, method, name):
    try:
        accepted = checked_id(value, "id") == value
    except ValueError:
        accepted = False
    assert allows(documented(path, method, name), value) == accepted


@pytest.mark.parametrize("value", ["1", "9", "10", "2", "123456789", "1000000000", str(MAX_VERSION),
                                   str(MAX_VERSION + 1), "9999999999", "0", "-1", "1.0", "v3", "", "3\n"])
def test_a_documented_version_is_what_checked_version_accepts(value):
    try:
        accepted = checked_version(value) == value
    except ValueError:
        accepted = False
    assert allows(documented("/models/{name}/versions/{version}", "get", "version"), value) == accepted


def test_job_and_session_ids_are_documented_as_generated():
    for path, name in [("/jobs/{job_id}", "job_id"), ("/sessions/{session_id}", "session_id")]:
        assert documented(path, "get", name)["pattern"] == SESSION_ID.pattern
    assert allows(documented("/jobs/{job_id}", "get", "job_id"), "5f0c3a9e2b6d4f1a8c7e9d0b1a2c3d4e")
    assert not allows(documented("/jobs/{job_id}", "get", "job_id"), "5F0C3A9E2B6D4F1A8C7E9D0B1A2C3D4E")


@pytest.mark.parametrize("value,accepted", [("champion", True), ("a-b_c", True), ("v", True), ("v3a", True),
                                            ("x" * 255, True), ("v3", False), ("V12", False), ("latest", False),
                                            ("LaTeSt", False), ("a b", False), ("", False), ("x" * 256, False)])
def test_a_documented_alias_is_one_mlflow_takes(value, accepted):
    """What MLflow refuses as an alias name (it answers 422 to PUT), reserved names included."""
    schema = documented("/models/{name}/aliases/{alias}", "put", "alias")
    assert (allows(schema, value) and not re.fullmatch(schema["not"]["pattern"], value)) == accepted
