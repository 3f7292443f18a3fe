"""Pretrained models: shipping writes weights and a manifest, loading checks the sha256, damage is a clear error."""

from __future__ import annotations

import json

import pytest
import torch

from model.training.checkpoint import save_checkpoint
from model.methods.registry import build_method, example_batch
from model.deployment.pretrained import (
    PRETRAINED_DIR,
    RUN_TIME_SETTINGS,
    PretrainedError,
    UnknownPretrained,
    get_pretrained,
    held_out_from_report,
    load_pretrained,
    pretrained_names,
    remeasure_shipped,
    ship_checkpoint,
    verify,
)
from tests.builders import report_for, ship_tiny, write_tiny_dataset


def test_shipping_strips_training_state_and_records_the_recipe(tmp_path):
    shipped = ship_tiny(tmp_path / "pretrained", report=report_for(), report_path="docs/results/x.json")
    content = torch.load(shipped.path, weights_only=True)
    assert content["optimizer"] is None and content["rng"] is None and content["step"] == 120
    manifest = json.loads((shipped.folder / "manifest.json").read_text())
    assert (manifest["method"], manifest["preset"], manifest["scale"]) == ("wskpn", "xs", 1)
    assert manifest["training"]["steps"] == 150 and manifest["training"]["seed"] == 7
    assert manifest["bytes"] == shipped.path.stat().st_size
    held_out = manifest["held_out"]
    assert held_out["status"] == "measured" and held_out["model"]["psnr"] == 30.5
    assert held_out["report"] == "docs/results/x.json"
    assert [peer["label"] for peer in held_out["peers"]] == ["oidn:high", "oidn-taa:high"]
    assert held_out["sequences"] == ["glass_s4", "moving_light_s4"]
    assert pretrained_names(tmp_path / "pretrained") == ["wskpn-xs-x1"]


def test_earlier_training_stages_are_recorded(tmp_path):
    torch.manual_seed(1)
    first = save_checkpoint(tmp_path / "first.pt", method=build_method("wskpn:xs", 1), step=400,
                            train_config={"steps": 400, "frames_per_sample": 8})
    shipped = ship_tiny(tmp_path / "pretrained", stages=[first])
    (stage,) = shipped.manifest["training"]["stages"]
    assert stage["step"] == 400 and stage["train_config"]["frames_per_sample"] == 8


def test_a_failed_reshipping_leaves_the_shipped_model_as_it_was(tmp_path):
    shipped = ship_tiny(tmp_path / "pretrained")
    weights, manifest = shipped.path.read_bytes(), (shipped.folder / "manifest.json").read_text()
    torch.manual_seed(9)  # other weights than the shipped ones
    other = save_checkpoint(tmp_path / "other.pt", method=build_method("wskpn:xs", 1), step=50)
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        ship_checkpoint(other, "wskpn-xs-x1", root=tmp_path / "pretrained", stages=[tmp_path / "missing.pt"])
    with pytest.raises(PretrainedError, match="0 rows"):
        ship_checkpoint(other, "wskpn-xs-x1", root=tmp_path / "pretrained", report=report_for(),
                        report_source="runs/other.pt")
    assert shipped.path.read_bytes() == weights and (shipped.folder / "manifest.json").read_text() == manifest
    verify(get_pretrained("wskpn-xs-x1", tmp_path / "pretrained"))


def test_without_a_report_the_held_out_metrics_are_pending(tmp_path):
    shipped = ship_tiny(tmp_path / "pretrained")
    assert shipped.held_out["status"] == "pending" and shipped.held_out_row() is None


def test_a_report_of_another_model_or_scale_is_refused(tmp_path):
    with pytest.raises(PretrainedError, match="0 rows from 'runs/other.pt'"):
        held_out_from_report(report_for(), "runs/other.pt", "wskpn", "xs", 1)
    with pytest.raises(PretrainedError, match="at scale 2"):
        held_out_from_report(report_for(scale=2), "runs/x/best.pt", "wskpn", "xs", 1)
    with pytest.raises(PretrainedError, match="not wskpn:s"):
        held_out_from_report(report_for(), "runs/x/best.pt", "wskpn", "s", 1)


def test_a_shipped_model_loads_with_its_weights(tmp_path):
    root = tmp_path / "pretrained"
    ship_tiny(root)
    torch.manual_seed(3)
    original = build_method("wskpn:xs", 1).eval()
    loaded = load_pretrained("wskpn-xs-x1", root=root)
    frame = example_batch(16, 16)
    with torch.no_grad():
        torch.testing.assert_close(loaded.step(frame, None)[0], original.step(frame, None)[0])


def test_damaged_missing_and_unknown_files_are_clear_errors(tmp_path):
    root = tmp_path / "pretrained"
    shipped = ship_tiny(root)
    data = bytearray(shipped.path.read_bytes())
    data[-100] ^= 0xFF
    shipped.path.write_bytes(bytes(data))
    with pytest.raises(PretrainedError, match="sha256 .* the manifest says .* damaged or was replaced"):
        load_pretrained("wskpn-xs-x1", root=root)
    shipped.path.unlink()
    with pytest.raises(PretrainedError, match="weights file .* is missing"):
        verify(get_pretrained("wskpn-xs-x1", root))
    (shipped.folder / "manifest.json").write_text("{not json")
    with pytest.raises(PretrainedError, match="not readable JSON"):
        get_pretrained("wskpn-xs-x1", root)
    with pytest.raises(UnknownPretrained, match="no pretrained model named 'nope' .*wskpn-xs-x1"):
        get_pretrained("nope", root)
    with pytest.raises(UnknownPretrained):
        get_pretrained("../pretrained", root)


@pytest.mark.parametrize("name", pretrained_names())
def test_every_model_in_the_repository_matches_its_manifest_and_runs(name):
    model = get_pretrained(name)
    assert model.folder.parent == PRETRAINED_DIR
    assert model.manifest["bytes"] < 3_000_000  # small enough to live in git
    verify(model)
    method = load_pretrained(name).for_inference()
    assert (method.name, method.preset, method.scale) == (model.method, model.preset, model.scale)
    frame = example_batch(16, 16)
    with torch.no_grad():
        output, state = method.step(frame, None)
        output, _ = method.step(frame, state)
    assert output.shape == (1, 3, 16 * model.scale, 16 * model.scale) and torch.isfinite(output).all()
    held_out = model.held_out
    assert held_out["status"] in ("measured", "pending")
    if held_out["status"] == "measured":
        assert held_out["model"]["psnr"] is not None and held_out["peers"]


@pytest.mark.parametrize("name", [name for name in pretrained_names() if name.startswith("fused-")])
def test_a_fused_model_trained_from_nothing_starts_with_the_settings_its_shipped_models_run(name):
    from model.methods.fused import SHIPPED_SETTINGS

    shipped = load_pretrained(name)
    expected = dict(SHIPPED_SETTINGS[shipped.scale])
    if name == "fused-high-x1":  # never trained with its sample mean (SHIPPED_SETTINGS' comment)
        expected["sample_mean_trust_power"] = 3.0
    assert {setting: getattr(shipped, setting) for setting in expected} == expected
    assert set(expected) | {"albedo_detail_frames"} == set(RUN_TIME_SETTINGS) == set(shipped.run_time_settings())
    assert shipped.run_time_settings() == {setting: getattr(shipped, setting) for setting in RUN_TIME_SETTINGS}


def test_evaluate_takes_a_pretrained_name(tmp_path, monkeypatch):
    import model.deployment.pretrained as pretrained
    from model.evaluation.evaluate import resolve_method

    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    ship_tiny(tmp_path / "pretrained")
    method, source = resolve_method("wskpn-xs-x1", 1)
    assert (method.label, source) == ("wskpn:xs", "pretrained:wskpn-xs-x1")


def test_names_no_model_can_have_are_simply_not_pretrained(tmp_path):
    from model.deployment.pretrained import is_pretrained

    ship_tiny(tmp_path / "pretrained")
    for name in ("0" * 600, "../pretrained", "Wskpn-XS-x1", "", "a/b"):
        assert not is_pretrained(name, tmp_path / "pretrained")
    assert is_pretrained("wskpn-xs-x1", tmp_path / "pretrained")


def test_a_fine_tune_of_a_shipped_model_keeps_its_recorded_stages(tmp_path):
    torch.manual_seed(1)
    first = save_checkpoint(tmp_path / "first.pt", method=build_method("wskpn:xs", 1), step=400,
                            train_config={"steps": 400, "frames_per_sample": 8})
    shipped = ship_tiny(tmp_path / "pretrained", stages=[first])
    old_sha, old_step = shipped.sha256, shipped.manifest["training"]["step"]
    torch.manual_seed(2)
    tuned = save_checkpoint(tmp_path / "tuned.pt", method=build_method("wskpn:xs", 1), step=90,
                            train_config={"steps": 100, "init_from": str(shipped.path)})
    reshipped = ship_checkpoint(tuned, "wskpn-xs-x1", root=tmp_path / "pretrained", after_shipped="wskpn-xs-x1")
    stages = reshipped.manifest["training"]["stages"]
    assert [stage["step"] for stage in stages] == [400, old_step]
    assert stages[1]["checkpoint"] == "pretrained/wskpn-xs-x1/model.pt" and stages[1]["sha256"] == old_sha
    assert reshipped.sha256 != old_sha and reshipped.manifest["training"]["step"] == 90
    with pytest.raises(UnknownPretrained):
        ship_checkpoint(tuned, "wskpn-xs-x1", root=tmp_path / "pretrained", after_shipped="no-such-model")


def test_a_shipped_model_reshipped_with_a_setting_keeps_its_dataset_record_and_a_new_dataset_replaces_it(tmp_path):
    root = tmp_path / "pretrained"
    data = write_tiny_dataset(tmp_path / "tiny")
    source = save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast", 1), step=30,
                             train_config={"steps": 30, "data": str(data)})
    shipped = ship_checkpoint(source, "fused-fast-x1", root=root, dataset_dir=data, dataset_script="render.sh")
    recorded = shipped.manifest["training"]["dataset"]
    assert recorded["digest"] and recorded["script"] == "render.sh"
    # the same weights with a run-time setting, on a machine without the dataset: its record stands
    reshipped = ship_checkpoint(shipped.path, "fused-fast-x1", root=root, after_shipped="fused-fast-x1",
                                unjitter_estimate=True)
    assert reshipped.manifest["training"]["dataset"] == recorded
    other = write_tiny_dataset(tmp_path / "other", size=(8, 8))
    tuned = save_checkpoint(tmp_path / "tuned.pt", method=build_method("fused:fast", 1), step=10,
                            train_config={"steps": 10, "data": str(other)})
    moved = ship_checkpoint(tuned, "fused-fast-x1", root=root, after_shipped="fused-fast-x1")
    assert moved.manifest["training"]["dataset"] == {"path": str(other), "script": None}  # not the old record


def test_a_shipped_model_remeasured_in_another_run_keeps_its_weights_and_training_record(tmp_path):
    root = tmp_path / "pretrained"
    shipped = ship_tiny(root, report=report_for(), report_path="docs/results/old.json")
    weights = shipped.path.read_bytes()
    newer = report_for(source="wskpn-xs-x1")
    newer["methods"][0]["metrics"]["psnr"] = 30.9
    remeasured = remeasure_shipped("wskpn-xs-x1", newer, "wskpn-xs-x1", "docs/results/new.json", root)
    assert remeasured.held_out_row()["psnr"] == 30.9 and remeasured.held_out["report"] == "docs/results/new.json"
    assert remeasured.path.read_bytes() == weights and remeasured.sha256 == shipped.sha256
    assert remeasured.manifest["training"] == shipped.manifest["training"]
    with pytest.raises(PretrainedError, match="0 rows from 'runs/other.pt'"):
        remeasure_shipped("wskpn-xs-x1", newer, "runs/other.pt", root=root)
    assert get_pretrained("wskpn-xs-x1", root).held_out_row()["psnr"] == 30.9  # a refused report changes nothing
    shipped.path.write_bytes(weights[:-1] + bytes([weights[-1] ^ 1]))
    with pytest.raises(PretrainedError, match="sha256"):  # numbers are never recorded for a file that is not it
        remeasure_shipped("wskpn-xs-x1", newer, "wskpn-xs-x1", root=root)


def test_a_shipped_fused_model_reshipped_with_another_recurrence_keeps_its_weights(tmp_path):
    from model.methods.fused import RECURRENCE_KEY

    root = tmp_path / "pretrained"
    torch.manual_seed(5)
    method = build_method("fused:fast", 1)
    method.set_history_before_kernel(False)
    source = save_checkpoint(tmp_path / "fused.pt", method=method, step=30, train_config={"steps": 30})
    shipped = ship_checkpoint(source, "fused-fast-x1", root=root)
    assert not load_pretrained("fused-fast-x1", root=root).history_before_kernel
    reshipped = ship_checkpoint(shipped.path, "fused-fast-x1", root=root, after_shipped="fused-fast-x1",
                                history_before_kernel=True)
    assert load_pretrained("fused-fast-x1", root=root).history_before_kernel
    before, after = (torch.load(model, weights_only=True)["model"] for model in (source, reshipped.path))
    assert before.keys() == after.keys() and float(after[RECURRENCE_KEY]) == 1.0
    assert all(torch.equal(before[key], after[key]) for key in before if key != RECURRENCE_KEY)
    assert reshipped.manifest["training"]["stages"][-1]["sha256"] == shipped.sha256
    with pytest.raises(PretrainedError, match="no choice of recurrence"):
        ship_tiny(root, history_before_kernel=True)


@pytest.mark.parametrize("setting, key, default, value, bad, refusal, missing", [
    pytest.param("kernel_max_pixels", "kernel_limit_pixels", 0, 32768, -1, "whole number of pixels",
                 "no output kernel to limit", id="kernel limit"),
    pytest.param("mean_max_frames", "mean_window_frames", 16, 8, 0, "whole number of frames", "no running mean",
                 id="mean window"),
    pytest.param("stale_test_sigmas", "stale_history_sigmas", 0.0, 2.0, -1.0, "finite number of standard errors",
                 "no running mean", id="stale-history test"),
    pytest.param("stale_region_pixels", "stale_region_window", 0, 33, 4, "odd whole number of pixels",
                 "no running mean", id="regional stale-history test"),
    pytest.param("sample_mean_frames", "sample_mean_window", 0, 8, -1, "whole number of frames >= 0",
                 "no spatial denoiser to feed a sample mean", id="sample mean"),
    pytest.param("sample_mean_trust_power", "sample_mean_share_power", 2.0, 3.0, 0.0, "finite number > 0",
                 "no spatial denoiser to feed a sample mean", id="sample mean trust"),
    pytest.param("unjitter_estimate", "estimate_unjittered", False, True, 1, "true or false",
                 "no spatial estimate to resample", id="unjittered estimate"),
])
def test_a_shipped_fused_model_reshipped_with_a_run_time_setting_keeps_its_weights(tmp_path, setting, key, default,
                                                                                   value, bad, refusal, missing):
    root = tmp_path / "pretrained"
    torch.manual_seed(6)
    source = save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast", 1), step=30,
                             train_config={"steps": 30})
    shipped = ship_checkpoint(source, "fused-fast-x1", root=root)
    assert getattr(load_pretrained("fused-fast-x1", root=root), setting) == default
    reshipped = ship_checkpoint(shipped.path, "fused-fast-x1", root=root, after_shipped="fused-fast-x1",
                                **{setting: value})
    assert getattr(load_pretrained("fused-fast-x1", root=root), setting) == value
    before, after = (torch.load(model, weights_only=True)["model"] for model in (source, reshipped.path))
    assert all(torch.equal(before[name], after[name]) for name in before if name != key)
    with pytest.raises(PretrainedError, match=refusal):
        ship_checkpoint(shipped.path, "fused-fast-x1", root=root, **{setting: bad})
    assert getattr(load_pretrained("fused-fast-x1", root=root), setting) == value  # a refused ship changes nothing
    with pytest.raises(PretrainedError, match=missing):
        ship_tiny(root, **{setting: value})


def test_a_2x_fused_model_reshipped_with_texture_detail_keeps_its_weights_and_a_1x_one_is_refused(tmp_path):
    root = tmp_path / "pretrained"
    torch.manual_seed(7)
    source = save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast", 2), step=30,
                             train_config={"steps": 30})
    shipped = ship_checkpoint(source, "fused-fast-x2", root=root)
    assert load_pretrained("fused-fast-x2", root=root).albedo_detail_frames == 0
    reshipped = ship_checkpoint(shipped.path, "fused-fast-x2", root=root, after_shipped="fused-fast-x2",
                                albedo_detail_frames=8)
    assert load_pretrained("fused-fast-x2", root=root).albedo_detail_frames == 8
    before, after = (torch.load(model, weights_only=True)["model"] for model in (source, reshipped.path))
    assert all(torch.equal(before[name], after[name]) for name in before if name != "albedo_detail_window")
    with pytest.raises(PretrainedError, match="whole number of frames >= 0"):
        ship_checkpoint(shipped.path, "fused-fast-x2", root=root, albedo_detail_frames=-1)
    one_x = save_checkpoint(tmp_path / "fused1.pt", method=build_method("fused:fast", 1), step=30,
                            train_config={"steps": 30})
    with pytest.raises(PretrainedError, match="scale 2"):
        ship_checkpoint(one_x, "fused-fast-x1", root=root, albedo_detail_frames=8)
    with pytest.raises(PretrainedError, match="no albedo to gather"):
        ship_tiny(root, albedo_detail_frames=8)


def test_shipping_with_a_setting_no_model_has_is_refused_by_name(tmp_path):
    root = tmp_path / "pretrained"
    source = save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast", 1), step=30,
                             train_config={"steps": 30})
    with pytest.raises(PretrainedError, match="no run-time setting sample_mean_power; settings: "):
        ship_checkpoint(source, "fused-fast-x1", root=root, sample_mean_power=3.0)
    assert not (root / "fused-fast-x1").exists()


def test_a_wskpn_model_reshipped_with_its_history_rectified_keeps_its_weights_and_a_fused_one_is_refused(tmp_path):
    root = tmp_path / "pretrained"
    shipped = ship_tiny(root)  # wskpn-xs-x1, shipped without the setting
    assert load_pretrained("wskpn-xs-x1", root=root).rectify_history is False
    before = torch.load(shipped.path, weights_only=True)["model"]
    reshipped = ship_checkpoint(shipped.path, "wskpn-xs-x1", root=root, after_shipped="wskpn-xs-x1",
                                rectify_history=True)
    assert load_pretrained("wskpn-xs-x1", root=root).rectify_history is True
    after = torch.load(reshipped.path, weights_only=True)["model"]
    assert (before["history_rectification"].item(), after["history_rectification"].item()) == (0.0, 1.0)
    assert all(torch.equal(before[name], after[name]) for name in before if name != "history_rectification")
    with pytest.raises(PretrainedError, match="rectify_history must be true or false"):
        ship_checkpoint(reshipped.path, "wskpn-xs-x1", root=root, rectify_history="yes")
    assert load_pretrained("wskpn-xs-x1", root=root).rectify_history is True  # a refused ship changes nothing
    fused = save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast", 1), step=30,
                            train_config={"steps": 30})
    with pytest.raises(PretrainedError, match="no accumulated history to rectify"):
        ship_checkpoint(fused, "fused-fast-x1", root=root, rectify_history=True)
    with pytest.raises(PretrainedError, match="only the fused family"):
        ship_checkpoint(reshipped.path, "wskpn-xs-x1", root=root, stale_test_sigmas=0.5)
