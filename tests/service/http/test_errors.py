"""service.http.errors on the real app: 405 names the allowed methods, JSON bodies that are not JSON or not sent as
JSON get 400 / 415 with messages saying what to change, never a bare validation error."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize(("method", "path", "allowed"), [
    ("PATCH", "/datasets/demo", "DELETE, GET"),
    ("PUT", "/datasets", "GET, POST"),
    ("POST", "/health", "GET"),
    ("GET", "/sessions/0123456789abcdef0123456789abcdef/frames", "POST"),
])
def test_a_wrong_method_is_405_with_the_allowed_ones(client, method, path, allowed):
    response = client.request(method, path)
    assert response.status_code == 405
    assert response.headers["allow"] == allowed
    error = response.json()["error"]
    assert error["code"] == "method_not_allowed"
    assert error["message"] == f"{method} is not allowed on {path}; allowed: {allowed}"


@pytest.mark.parametrize("path", ["/sessions", "/jobs"])
def test_a_json_body_sent_as_another_type_is_415_naming_it(client, path):
    response = client.post(path, content=b'{"model": "x"}', headers={"content-type": "text/plain"})
    assert response.status_code == 415
    error = response.json()["error"]
    assert error["code"] == "unsupported_media_type"
    assert error["message"].startswith("Content-Type text/plain is not accepted here")
    assert "application/json" in error["message"]
    missing = client.post(path, content=b'{"model": "x"}')
    assert missing.status_code == 415 and missing.json()["error"]["message"].startswith("no Content-Type")


def test_a_body_that_is_not_json_is_400_with_the_position(client):
    response = client.post("/sessions", content=b'{"model": ', headers={"content-type": "application/json"})
    assert response.status_code == 400
    error = response.json()["error"]
    assert error["code"] == "invalid_json" and error["details"] == {"position": 10}
    assert error["message"].startswith("the body is not valid JSON at character 10")
    binary = client.put("/models/m/aliases/a", content=b"\xff\xfe\x00", headers={"content-type": "application/json"})
    assert binary.status_code == 400 and binary.json()["error"]["code"] == "invalid_json"


def test_a_valid_json_body_with_a_bad_field_is_still_422_naming_the_field(client):
    response = client.post("/sessions", json={"model": "x", "on_gap": "sometimes"})
    assert response.status_code == 422
    assert "on_gap" in response.json()["error"]["message"]


@pytest.mark.parametrize(("body", "fragment"), [
    (b"[" * 100_000, "nested too deeply"),
    (b'{"model": ' + b"9" * 5000 + b"}", "an integer has too many digits"),
    (b"\xff\xfe\x00", "it is not UTF-8"),
])
def test_json_bodies_the_parser_refuses_are_400_saying_why(client, body, fragment):
    response = client.post("/jobs", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 400, response.text
    error = response.json()["error"]
    assert error["code"] == "invalid_json" and fragment in error["message"], error


@pytest.mark.parametrize(("number", "reason"), [(28, "no space left"), (30, "storage is read-only")])
def test_full_or_read_only_storage_is_507_without_server_paths(client, monkeypatch, caplog, number, reason):
    import errno

    from service.datasets import receive

    def fail(*args, **kwargs):
        raise OSError(number, errno.errorcode[number], "/srv/secret/var/staging/upload-1/upload.bin")

    monkeypatch.setattr(receive, "save_stream", fail)
    with caplog.at_level("ERROR", logger="denoiser.api"):
        response = client.post("/datasets", content=b"PK\x03\x04", headers={"content-type": "application/zip"})
    assert response.status_code == 507, response.text
    error = response.json()["error"]
    assert error["code"] == "insufficient_storage" and reason in error["message"]
    assert "/srv/secret" not in response.text
    assert "/srv/secret/var/staging/upload-1/upload.bin" in caplog.text  # the operator still finds it
    assert error["details"]["reference"] in caplog.text


def test_an_unexpected_error_is_500_without_its_message(client, monkeypatch):
    from service.datasets import catalog

    monkeypatch.setattr(catalog, "list_datasets", lambda storage: open("/srv/secret/missing"))
    response = client.get("/datasets")
    assert response.status_code == 500
    assert "/srv/secret" not in response.text
    assert response.json()["error"]["message"].startswith("internal error (FileNotFoundError)")


@pytest.mark.parametrize("error_type, status", [("NotFound", 404), ("Invalid", 422), ("Conflict", 409),
                                                ("Unavailable", 503)])
def test_domain_errors_become_their_status_with_the_one_error_shape(error_type, status):
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from service.http.errors import install_error_handlers
    from core import errors

    app = FastAPI()
    install_error_handlers(app)

    @app.get("/fails")
    def fails() -> None:
        raise getattr(errors, error_type)("some_code", "what went wrong", {"name": "x"})

    response = TestClient(app).get("/fails")
    assert response.status_code == status
    assert response.json() == {"error": {"code": "some_code", "message": "what went wrong", "details": {"name": "x"}}}


def _errors_of_the_table():
    from core.job_store import JobFinished, JobNotFound
    from core.registry import ConstraintNotMet, NoAutoCandidates, RegistryUnavailable, UnknownModelError
    from service.datasets import errors as upload
    from service.sessions import store
    from service.sessions.models import SessionModelInvalid

    return [
        (UnknownModelError("model 'm' does not exist"), 404, "not_found", None),
        (NoAutoCandidates("no candidates", {"needed_tags": ["validation_psnr"]}), 404, "no_candidate_model",
         {"needed_tags": ["validation_psnr"]}),
        (ConstraintNotMet("none meets it", {"candidates": 2}), 422, "constraint_not_met", {"candidates": 2}),
        (RegistryUnavailable("down"), 503, "registry_unavailable", None),
        (JobNotFound("job 'j' does not exist"), 404, "not_found", None),
        (JobFinished("j", "succeeded"), 409, "job_finished", {"state": "succeeded"}),
        (SessionModelInvalid("untrained", code="untrained_method"), 422, "untrained_method", None),
        (store.SessionLimitReached("too many"), 429, "too_many_sessions", None),
        (store.FrameRejected("gap", code="frame_gap"), 409, "frame_gap", None),
        (upload.UploadTooLarge("payload_too_large", "too big", {"limit_bytes": 1}), 413, "payload_too_large",
         {"limit_bytes": 1}),
        (upload.UnknownDataset("not_found", "no such dataset"), 404, "not_found", None),
    ]


def test_every_route_error_gets_its_status_and_code_from_the_one_table():
    from fastapi import FastAPI
    from fastapi.testclient import TestClient

    from service.http.errors import domain_errors, install_error_handlers

    cases = _errors_of_the_table()
    app = FastAPI()
    install_error_handlers(app)

    @app.get("/raise/{index}")
    def raises(index: int) -> None:
        raise cases[index][0]

    @app.get("/wrapped")
    def wrapped() -> None:
        with domain_errors():  # where a route needs the ApiError itself, and a ValueError means bad input
            raise ValueError("version 'x' is not a positive integer")

    client = TestClient(app)
    for index, (error, status, code, details) in enumerate(cases):
        response = client.get(f"/raise/{index}")
        assert response.status_code == status, (error, response.text)
        assert response.json()["error"] == {"code": code, "message": str(error), "details": details}
    wrapped_response = client.get("/wrapped")
    assert wrapped_response.status_code == 422 and wrapped_response.json()["error"]["code"] == "invalid_request"


def test_no_route_keeps_a_map_of_its_own():
    import re
    from pathlib import Path

    from service.http.errors import ERROR_STATUS

    names = {cls.__name__ for cls in ERROR_STATUS if cls is not ValueError}
    routes = Path(__file__).resolve().parents[3] / "service" / "http" / "routes"
    for path in routes.glob("*.py"):
        # An error of the table caught and answered with a status written there would be a second map.
        for caught, handler in re.findall(r"except \(?([\w., ]+?)\)?(?: as \w+)?:\n(?=([^\n]*\n))",
                                          path.read_text()):
            classes = {name.strip().split(".")[-1] for name in caught.split(",")}
            assert not (classes & names and re.search(r"ApiError\(\d", handler)), f"{path.name}: {caught}"
