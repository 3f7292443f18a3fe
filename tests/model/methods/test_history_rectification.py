"""History rectification as a run-time setting of WSKPN, AFN, JNDS and MUNet (model/methods/history_rectification.py):
what the clip does to a stale history, and how the setting is recorded, loaded and refused."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from model.training.checkpoint import load_method, save_checkpoint
from model.methods.afn import temporal_accumulate
from model.methods.history_rectification import RECTIFY_KEY
from model.methods.registry import build_method
from model.ops.demodulate import demodulate
from tests.builders import static_frame

METHODS = ("wskpn:xs", "afn:xs")  # they accumulate: the accumulated history has a known answer
WITH_THE_SETTING = (*METHODS, "jnds:xs", "jnds:xs-int8", "munet:xs")


def lit(level: float, seed: int = 0):
    """A still wall lit evenly at ``level``: the history passes the geometry test, so only a clip can reject it."""
    frame = static_frame(size=12, seed=seed)
    return dataclasses.replace(frame, color=torch.full_like(frame.color, level))


def accumulated_after_the_light_changed(method) -> torch.Tensor:
    """The accumulated (demodulated) radiance of the second of two frames, the light 4x brighter in the second."""
    _, state = method.step(lit(1.0), None)
    _, state = method.step(lit(4.0, seed=1), state)
    return state["irradiance"] if "irradiance" in state else state["accumulated"]


@pytest.mark.parametrize("name", METHODS)
def test_the_clip_rejects_a_history_the_light_left_and_without_it_the_mean_keeps_it(name):
    method = build_method(name).eval()
    current, _ = demodulate(lit(4.0).color, lit(4.0).albedo)
    with torch.no_grad():
        plain = accumulated_after_the_light_changed(method)
        method.set_rectify_history(True)
        rectified = accumulated_after_the_light_changed(method)
    # two frames: the running mean of 1 and 4 (demodulated), and with the clip the history is pulled onto the new
    # frame's flat neighbourhood, so only the new light is left
    torch.testing.assert_close(plain, current * 2.5 / 4.0)
    torch.testing.assert_close(rectified, current)


def test_afns_accumulation_is_clipped_only_when_asked():
    radiance, _ = demodulate(lit(4.0).color, lit(4.0).albedo)
    first, _ = demodulate(lit(1.0).color, lit(1.0).albedo)
    state = {"accumulated": first, "count": torch.ones_like(first[:, :1]), **{
        key: getattr(lit(1.0), key) for key in ("depth", "normal", "jitter")}}
    frame = lit(4.0, seed=1)
    plain, _ = temporal_accumulate(radiance, frame, state)
    rectified, _ = temporal_accumulate(radiance, frame, state, rectify=True)
    torch.testing.assert_close(plain, radiance * 2.5 / 4.0)
    torch.testing.assert_close(rectified, radiance)


@pytest.mark.parametrize("name", WITH_THE_SETTING)
def test_the_setting_is_recorded_with_the_weights_and_older_checkpoints_load_without_it(name, tmp_path):
    method = build_method(name)
    assert not method.rectify_history and method.run_time_settings() == {"rectify_history": False}
    method.set_rectify_history(True)
    loaded = load_method(save_checkpoint(tmp_path / "on.pt", method=method))
    assert loaded.rectify_history and loaded.run_time_settings() == {"rectify_history": True}
    older = {key: value for key, value in method.state_dict().items() if key != RECTIFY_KEY}
    fresh = build_method(name)
    fresh.set_rectify_history(True)
    fresh.load_state_dict(older)
    assert not fresh.rectify_history


@pytest.mark.parametrize("value", [1, "true", None])
def test_a_setting_that_is_not_a_bool_is_refused(value):
    with pytest.raises(ValueError, match="rectify_history must be true or false"):
        build_method("wskpn:xs").set_rectify_history(value)


def test_jnds_filters_its_lobes_history_clipped_to_this_frame_only_when_asked(monkeypatch):
    import model.methods.jnds as jnds

    seen = []
    original = jnds.hierarchical_filter

    def recording(current, history, *args, **kwargs):
        seen.append((current, history))
        return original(current, history, *args, **kwargs)

    monkeypatch.setattr(jnds, "hierarchical_filter", recording)
    method = build_method("jnds:xs", 1).eval()
    with torch.no_grad():
        _, state = method.step(lit(1.0), None)
        state = {**state, "diffuse": state["diffuse"] * 100.0}  # a history far off what this frame shows
        for rectify in (False, True):
            method.set_rectify_history(rectify)
            seen.clear()
            method.step(lit(1.0, seed=1), state)
            current, history = seen[0]  # the diffuse lobe
            # a flat frame's clip box is its value: the clipped history is the frame itself
            assert torch.allclose(history, current, atol=1e-4) is rectify


def test_munet_blends_its_radiance_history_clipped_to_this_frames_samples_only_when_asked():
    method = build_method("munet:xs", 1).eval()
    inner = (slice(None), slice(None), slice(2, -2), slice(2, -2))  # away from the kernels' borders
    with torch.no_grad():
        _, state = method.step(lit(1.0), None)
        state = {**state, "radiance": state["radiance"] * 100.0}  # an accumulated radiance far off this frame
        for rectify in (False, True):
            method.set_rectify_history(rectify)
            _, after = method.step(lit(1.0, seed=1), state)
            # a flat frame's clip box is its value, so the blend of the clipped history and the frame is the frame,
            # whatever weight the network predicts
            assert torch.allclose(after["radiance"][inner], torch.ones_like(after["radiance"][inner]),
                                  atol=1e-3) is rectify
