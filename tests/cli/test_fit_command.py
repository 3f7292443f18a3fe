"""`denoiser fit`: a real tiny run (two WSKPN presets, a few steps, tiny synthetic data) tracked in MLflow that
picks, registers, tags and aliases; a second run reuses both presets; the choice is what model "auto" finds."""

from __future__ import annotations

import json
import uuid

import pytest

from cli.main import main
from core.registry import Registry, choose_auto
from core.storage import Storage
from tests.builders import write_tiny_dataset
from tests.service.session_fixtures import shared_registry


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("fit-cli") / "data")


def fit_args(data, out, name, *extra) -> list[str]:
    return ["fit", "--data", str(data), "--method", "wskpn", "--presets", "xs,s", "--target", "within=100",
            "--steps", "2", "--crop", "8", "--frames-per-sample", "2", "--batch", "2", "--warmup", "0",
            "--time-at", "16x16", "--timing-frames", "2", "--threads", "1", "--device", "cpu", "--out", str(out),
            "--register-as", name, "--tracking-uri", shared_registry().uri, "--experiment", "fit-tests", *extra]


def test_a_tiny_fit_trains_picks_registers_and_reuses(data, tmp_path, capsys):
    name = f"wskpn-fit-{uuid.uuid4().hex[:8]}"
    out = tmp_path / "fit"
    assert main(fit_args(data, out, name)) == 0
    captured = capsys.readouterr()
    # within=100: the largest (s, by FLOPs per pixel) trains first and sets the bar; xs clears it.
    assert "| **xs** (chosen) |" in captured.out and "| s |" in captured.out
    assert "choice: xs: the smallest preset with validation PSNR within 100 dB of the largest" in captured.out
    assert f"registered: models:/{name}/" in captured.out and "alias 'fitted'" in captured.out
    assert "timing xs at 16x16" in captured.err and "measuring s on the validation split" in captured.err
    ladder = json.loads((out / "ladder.json").read_text())
    assert ladder["chosen"] == "xs" and ladder["met"] and ladder["timing"]["resolution"] == "16x16"
    assert [(r["preset"], r["status"]) for r in ladder["ladder"]] == [("xs", "trained"), ("s", "trained")]
    assert ladder["ladder"][0]["flops_per_pixel"] < ladder["ladder"][1]["flops_per_pixel"]

    registry = Registry(shared_registry().uri, Storage(tmp_path / "cache").ensure())
    model = registry.get_model(name)
    assert model.aliases == {"fitted": ladder["registered"]["version"]}
    by_preset = {v.preset: v for v in model.versions}
    assert set(by_preset) == {"xs", "s"}  # each preset's training registered its version
    chosen = by_preset["xs"]
    assert chosen.version == ladder["registered"]["version"] and chosen.aliases == ["fitted"]
    for version in by_preset.values():
        assert version.tags["ms_per_frame_resolution"] == "16x16" and version.tags["ms_per_frame_threads"] == "1"
        assert version.metrics["ms_per_frame"] > 0 and "validation_psnr" in version.metrics
        assert version.tags["fit_key"] == ladder["fit_key"] and version.metrics["validation_flip"] >= 0
    client = registry.client
    parent = client.get_run(ladder["run_id"])
    assert parent.data.params["chosen_preset"] == "xs" and parent.data.params["target"] == "within=100"
    assert {"ladder.json", "ladder.md"} <= {a.path for a in client.list_artifacts(parent.info.run_id)}
    child = client.get_run(chosen.run_id)
    assert child.data.tags["mlflow.parentRunId"] == parent.info.run_id

    # Sessions with model "auto" choose among the tagged versions: the smallest with the PSNR floor.
    choice = choose_auto(min_psnr=0.001, family="wskpn", registry=registry)
    assert choice.info.preset == "xs" and "the smallest of the" in choice.reason

    # Again: both presets come from the output folder, nothing new is registered.
    assert main(fit_args(data, out, name, "--quiet")) == 0
    again = json.loads((out / "ladder.json").read_text())
    assert [r["status"] for r in again["ladder"]] == ["reused-checkpoint", "reused-checkpoint"]
    assert len(registry.get_model(name).versions) == 2


def test_an_unmet_target_exits_1_and_bad_input_exits_2(data, tmp_path, capsys):
    name = f"wskpn-fit-{uuid.uuid4().hex[:8]}"
    args = fit_args(data, tmp_path / "fit", name, "--no-tracking", "--quiet")
    args[args.index("within=100")] = "ms=0.000001@16x16"  # no preset is that fast: nothing is trained
    assert main(args) == 1
    captured = capsys.readouterr()
    assert "no preset runs within 1e-06 ms per frame at 16x16" in captured.err
    assert not any(path.name.startswith(("xs-", "s-")) for path in (tmp_path / "fit").iterdir())

    args[args.index("ms=0.000001@16x16")] = "psnr=thirty"
    assert main(args) == 2
    assert "denoiser fit: error: target 'psnr=thirty'" in capsys.readouterr().err
