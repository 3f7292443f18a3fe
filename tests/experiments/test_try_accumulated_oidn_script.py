"""experiments/try_accumulated_oidn.py: OIDN on the running mean of the noisy frames, the model with the sample mean
set, and the experiment end to end on a tiny dataset."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from model.training.checkpoint import load_method, save_checkpoint
from model.methods.fused import frame_samples
from model.methods.registry import build_method
from tests.builders import load_script, static_frame, write_tiny_dataset

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "experiments" / "try_accumulated_oidn.py"


experiment = load_script("try_accumulated_oidn", "experiments")


def test_oidn_reads_the_mean_of_the_frames_and_a_cut_restarts_it():
    frames = [static_frame(size=8, seed=seed) for seed in range(3)]
    method = experiment.AccumulatedOIDN("fast", max_frames=4, stale_sigmas=0)
    state = None
    for frame in frames:
        _, state = method.step(frame, state)
    torch.testing.assert_close(state["samples"], sum(frame_samples(frame) for frame in frames) / 3)
    cut = static_frame(size=8, seed=3, cut=True)
    _, after_cut = method.step(cut, state)
    assert torch.equal(after_cut["samples"], frame_samples(cut)) and torch.all(after_cut["count"] == 1)


def test_the_variant_checkpoint_is_the_model_with_the_sample_mean_and_other_models_are_refused(tmp_path):
    save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast"))
    variant = experiment.with_sample_mean(str(tmp_path / "fused.pt"), 6, tmp_path / "variant.pt")
    assert load_method(variant).sample_mean_frames == 6
    save_checkpoint(tmp_path / "wskpn.pt", method=build_method("wskpn"))
    with pytest.raises(ValueError, match="needs a 1x fused model"):
        experiment.with_sample_mean(str(tmp_path / "wskpn.pt"), 6, tmp_path / "other.pt")


def test_the_experiment_runs_on_a_dataset_and_refuses_a_missing_one(tmp_path):
    data = write_tiny_dataset(tmp_path / "tiny")
    result = subprocess.run([sys.executable, str(SCRIPT), "--data", str(data), "--split", "validation",
                             "--threads", "1", "--report", str(tmp_path / "report.json")],
                            capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    for label in ("accumulated-oidn:fast", "fused-sample-mean.pt", "oidn-taa:fast", "oidn:high"):
        assert label in result.stdout
    report = json.loads((tmp_path / "report.json").read_text())
    assert [entry["label"] for entry in report["methods"]] == ["fused:fast", "accumulated-oidn:fast", "fused:fast",
                                                               "oidn-taa:fast", "oidn:high"]
    missing = subprocess.run([sys.executable, str(SCRIPT), "--data", str(tmp_path / "none")],
                             capture_output=True, text=True, cwd=ROOT)
    assert missing.returncode == 2 and "try_accumulated_oidn:" in missing.stderr
