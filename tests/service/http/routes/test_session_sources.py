"""/sessions on anything `denoiser evaluate` runs: methods without weights by name, pretrained models, and the
404 / 422 answers for names that are none of these or malformed."""

from __future__ import annotations

import pytest

import model.deployment.pretrained as pretrained
from model.io.exr import decode_image_exr
from model.methods.base import inference_outputs
from model.methods.registry import build_method, method_buffers
from tests.builders import error_message, ship_tiny
from tests.service.session_fixtures import (  # noqa: F401 (api: a fixture)
    MODEL_NAME,
    api,
    assert_same_image,
    assert_same_image_after_half_history,
    post_frame,
    stream_frames,
)

__all__ = ["api"]


@pytest.mark.parametrize("name, scale, label", [("oidn:high", None, "oidn:high"), ("svgf", 2, "svgf:default"),
                                                ("accumulation:fast", None, "accumulation:fast")])
def test_a_method_by_name_streams_as_it_runs_in_process(api, name, scale, label):
    client, _ = api()
    body = {"model": name} | ({"scale": scale} if scale else {})
    response = client.post("/sessions", json=body)
    assert response.status_code == 201, response.text
    session = response.json()
    method, preset = label.split(":")
    assert session["model"] == {"name": label, "version": None, "alias": None, "method": method, "preset": preset,
                                "scale": scale or 1, "params": 0, "source": "method",
                                "buffers": list(method_buffers(method))}
    frames = stream_frames(3, seed=5)
    expected = inference_outputs(build_method(label, scale or 1), frames)
    for index, frame in enumerate(frames):
        answer = post_frame(client, session["id"], frame)
        assert answer.status_code == 200, answer.text
        assert answer.headers["x-history"] == ("started" if index == 0 else "continued")
        assert_same_image(decode_image_exr(answer.content), expected[index])


def test_a_method_session_continues_after_a_restart(api):
    frames = stream_frames(3, seed=2)
    expected = inference_outputs(build_method("oidn-taa:fast", 1), frames)
    client, _ = api()
    session = client.post("/sessions", json={"model": "oidn-taa:fast"}).json()
    for frame in frames[:2]:
        assert post_frame(client, session["id"], frame).status_code == 200
    restarted, _ = api()
    answer = post_frame(restarted, session["id"], frames[2])
    assert answer.status_code == 200 and answer.headers["x-history"] == "continued"
    assert_same_image_after_half_history(decode_image_exr(answer.content), expected[2])


def test_a_pretrained_model_by_name_streams_its_shipped_weights(api, tmp_path, monkeypatch):
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    shipped = ship_tiny(tmp_path / "pretrained", "wskpn-xs-x1")
    client, _ = api()
    response = client.post("/sessions", json={"model": "wskpn-xs-x1"})
    assert response.status_code == 201, response.text
    model = response.json()["model"]
    assert (model["source"], model["method"], model["preset"], model["version"]) == \
        ("pretrained", "wskpn", "xs", shipped.sha256[:12])
    frames = stream_frames(2, seed=4)
    expected = inference_outputs(pretrained.load_pretrained("wskpn-xs-x1"), frames)
    for index, frame in enumerate(frames):
        answer = post_frame(client, response.json()["id"], frame)
        assert answer.status_code == 200, answer.text
        assert_same_image(decode_image_exr(answer.content), expected[index])


def test_a_damaged_pretrained_file_is_a_clear_422(api, tmp_path, monkeypatch):
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    shipped = ship_tiny(tmp_path / "pretrained", "wskpn-xs-x1")
    shipped.path.write_bytes(shipped.path.read_bytes()[:-10] + b"0123456789")
    client, _ = api()
    message = error_message(client.post("/sessions", json={"model": "wskpn-xs-x1"}), 422, "model_not_loadable")
    assert "sha256" in message and "damaged or was replaced" in message and "git checkout" in message
    shipped.path.unlink()
    message = error_message(client.post("/sessions", json={"model": "wskpn-xs-x1"}), 422, "model_not_loadable")
    assert "is missing" in message


def test_an_unknown_name_is_404_listing_what_exists(api):
    client, _ = api()
    response = client.post("/sessions", json={"model": "no-such-model"})
    message = error_message(response, 404, "not_found")
    assert "model 'no-such-model' does not exist" in message
    details = response.json()["error"]["details"]
    assert MODEL_NAME in details["registered"]
    assert details["pretrained"] == pretrained.pretrained_names()
    assert "oidn[:fast|balanced|high]" in details["methods"] and "svgf[:default|rectified]" in details["methods"]
    assert not any(name.startswith(("wskpn", "fused")) for name in details["methods"])  # learned: not by name
    assert "oidn[:fast|balanced|high]" in message
    error_message(client.post("/sessions", json={"model": "nomethod:high"}), 404, "not_found")


@pytest.mark.parametrize("body, code, words", [
    ({"model": "oidn/high"}, "invalid_model_name", "holds '/'"),
    ({"model": "oidn:high:x"}, "invalid_model_name", "one ':'"),
    ({"model": "oidn:"}, "invalid_model_name", "one ':'"),
    ({"model": " svgf"}, "invalid_model_name", "spaces"),
    ({"model": "oidn:ultra"}, "unknown_preset", "presets: fast, balanced, high"),
    ({"model": "wskpn:s"}, "untrained_method", "would run untrained"),
    ({"model": "oidn:high", "alias": "champion"}, "invalid_request", "version and alias go with registered"),
    ({"model": "svgf", "version": "2"}, "invalid_request", "version and alias go with registered"),
    ({"model": "svgf", "scale": 3}, "invalid_request", "scale"),
    ({"model": MODEL_NAME, "scale": 1}, "unsupported_scale", "runs at scale 2"),
])
def test_malformed_or_unfit_names_are_422_in_our_words(api, body, code, words):
    client, _ = api()
    message = error_message(client.post("/sessions", json=body), 422, code)
    assert words in message
    assert "MLflow" not in message and "INVALID_PARAMETER" not in message


def test_a_pretrained_name_with_an_alias_before_registration_says_how_to_register(api, tmp_path, monkeypatch):
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    ship_tiny(tmp_path / "pretrained", "wskpn-xs-x1")
    client, _ = api()
    message = error_message(client.post("/sessions", json={"model": "wskpn-xs-x1", "alias": "pretrained"}), 404,
                       "not_found")
    assert "denoiser pretrained --register" in message
