"""ONNX export of the per-frame step: the exported graph, run with onnxruntime over a short sequence with its
history fed back, matches PyTorch within the stated tolerance; methods that cannot be exported say why."""

from __future__ import annotations

import json

import pytest
import torch

pytest.importorskip("onnxruntime")

from model.deployment.export import (  # noqa: E402
    SPATIAL_INPUT,
    ExportError,
    Stages,
    check_export,
    example_inputs,
    export_step,
    run_exported,
)
from model.methods.registry import build_method  # noqa: E402
from model.deployment.pretrained import load_pretrained, pretrained_names  # noqa: E402


def seeded(name: str, scale: int):
    torch.manual_seed(4)
    return build_method(name, scale)


@pytest.mark.parametrize("name, scale", [("wskpn:xs", 1), pytest.param("jnds:xs", 2, marks=pytest.mark.slow)])
def test_an_exported_method_matches_pytorch_over_a_sequence(tmp_path, name, scale):
    method = seeded(name, scale)
    said = []
    stages = Stages(said.append)
    info = export_step(method, tmp_path / "step.onnx", height=16, width=24, stages=stages)
    assert list(stages.seconds) == ["prepare", "torch.export", "onnx", "optimize", "write"]
    assert [line.split(":")[0] for line in said] == list(stages.seconds)
    assert info["outputs"]["output"] == [1, 3, 16 * scale, 24 * scale]
    assert set(info["inputs"]) == {"color", "albedo", "normal", "depth", "motion", "jitter"}
    assert check_export(method, tmp_path / "step.onnx", info, frames=4) <= 1  # within 1e-4 abs + 1e-4 rel
    import onnx

    stored = json.loads({p.key: p.value for p in onnx.load(tmp_path / "step.onnx").metadata_props}["denoiser"])
    assert stored["state"] == info["state"] and stored["method"] == method.name


def test_the_history_is_carried_through_the_state_outputs(tmp_path):
    """A check that could not fail if the state were ignored: fed back, the outputs differ from a fresh start."""
    method = seeded("wskpn:xs", 1)
    info = export_step(method, tmp_path / "step.onnx", height=16, width=16)
    frames = [example_inputs(method, 16, 16, seed=seed)[0] for seed in (1, 2, 3)]
    carried = run_exported(tmp_path / "step.onnx", frames, info["state"])
    fresh = run_exported(tmp_path / "step.onnx", frames[2:], info["state"])
    assert not torch.allclose(carried[2], fresh[0], atol=1e-3)


@pytest.mark.parametrize("name", pretrained_names())
def test_every_shipped_model_exports_and_matches_pytorch_or_says_why(tmp_path, name):
    method = load_pretrained(name)
    if method.preset.endswith("-int8"):
        with pytest.raises(ExportError, match="eager-mode int8 quantized modules"):
            export_step(method, tmp_path / "model.onnx", height=16, width=16)
        return
    info = export_step(method, tmp_path / "model.onnx", height=16, width=16)
    # The fused family's OIDN runs outside the exported network: its output is an input of the export.
    assert (SPATIAL_INPUT in info["inputs"]) == (method.name == "fused")
    if method.name == "fused":
        assert "OIDN" in info["spatial_estimate"]
    assert check_export(method, tmp_path / "model.onnx", info, frames=3) <= 1


@pytest.mark.parametrize("name, scale, words", [
    ("oidn:high", 1, "OIDN's native library"),
    ("oidn-taa:high", 1, "OIDN's native library"),
    ("svgf", 1, "filter without weights"),
    ("jnds:xs-int8", 2, "eager-mode int8 quantized modules"),
])
def test_what_cannot_be_exported_says_why(tmp_path, name, scale, words):
    with pytest.raises(ExportError, match=words):
        export_step(build_method(name, scale), tmp_path / "x.onnx")
    assert not (tmp_path / "x.onnx").exists()


def test_a_fused_model_with_a_sample_mean_exports_its_step_on_the_single_frame_and_says_so(tmp_path):
    method = seeded("fused:fast", 1)
    method.set_sample_mean_frames(8)  # in PyTorch OIDN's input comes from the state, inside the step
    info = export_step(method, tmp_path / "x.onnx", height=16, width=16)
    assert "not exported" in info["sample_mean"] and "single frame" in info["sample_mean"]
    assert method.sample_mean_frames == 8  # the export ran a copy
    assert {"samples", "samples_count"}.isdisjoint(info["state"])
    assert check_export(method, tmp_path / "x.onnx", info, frames=3) <= 1
    plain = export_step(seeded("fused:fast", 1), tmp_path / "y.onnx", height=16, width=16)
    assert plain["sample_mean"] is None


def test_a_2x_fused_model_with_texture_detail_exports_it_and_matches_pytorch_on_jittered_frames(tmp_path):
    method = seeded("fused:fast", 2)
    method.set_albedo_detail_frames(8)  # the gathered albedo is state, fed back like the history
    info = export_step(method, tmp_path / "x.onnx", height=16, width=16)
    assert {"albedo_sum", "albedo_weight"} <= set(info["state"])
    assert info["state"]["albedo_sum"] == [1, 3, 32, 32]
    assert check_export(method, tmp_path / "x.onnx", info, frames=4) <= 1  # the check's frames are jittered


def test_torchscript_is_refused_with_the_reason(tmp_path):
    with pytest.raises(ExportError, match="custom autograd functions"):
        export_step(seeded("wskpn:xs", 1), tmp_path / "x.pt", "torchscript")
