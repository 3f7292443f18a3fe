"""experiments/try_lowband_correction.py: the low-band correction's arithmetic, its gates, and the experiment end to end
on a tiny dataset."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from model.methods.oidn_taa import reinhard
from model.methods.registry import build_method
from tests.builders import load_script, static_frame, write_tiny_dataset

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "experiments" / "try_lowband_correction.py"


experiment = load_script("try_lowband_correction", "experiments")


def checker(size: int, low: float, high: float) -> torch.Tensor:
    pattern = (torch.arange(size).view(-1, 1) + torch.arange(size).view(1, -1)) % 2
    return (low + (high - low) * pattern.float()).expand(1, 3, size, size).clone()


def test_the_blur_keeps_a_constant_and_spreads_an_impulse_over_a_unit_sum():
    constant = torch.full((1, 3, 12, 12), 0.7)
    torch.testing.assert_close(experiment.gaussian_blur(constant, 2.0), constant)
    impulse = torch.zeros(1, 1, 25, 25)
    impulse[..., 12, 12] = 1.0
    blurred = experiment.gaussian_blur(impulse, 2.0)
    assert blurred.sum().item() == pytest.approx(1.0, abs=1e-5)
    assert blurred[..., 12, 12].item() == blurred.max().item() < 0.05


def test_without_the_gate_the_output_is_kept_and_with_it_takes_the_estimates_low_band_keeping_its_detail():
    output, estimate = checker(32, 0.2, 0.6), torch.full((1, 3, 32, 32), 1.0)
    torch.testing.assert_close(experiment.low_band_corrected(output, estimate, 0.0, 4.0), output, atol=1e-5,
                               rtol=1e-5)
    corrected = reinhard(experiment.low_band_corrected(output, estimate, 1.0, 4.0))
    inner = (slice(None), slice(None), slice(8, 24), slice(8, 24))  # away from the border's replicated rows
    # the low band moves to the estimate's (0.5 in x / (1 + x)), within the ratio's offset
    torch.testing.assert_close(experiment.gaussian_blur(corrected, 4.0)[inner], torch.full((1, 3, 16, 16), 0.5),
                               atol=0.01, rtol=0)
    # the checker's contrast, as a ratio of its two values, is the output's
    mapped = reinhard(output)
    assert (corrected[0, 0, 9, 8] / corrected[0, 0, 8, 8]).item() == pytest.approx(
        (mapped[0, 0, 9, 8] / mapped[0, 0, 8, 8]).item(), rel=1e-4)


def test_the_stale_gate_opens_only_where_the_output_is_off_the_noisy_frame():
    frame = static_frame(size=32, seed=1)  # noisy colour uniform in [0, 2): mean 1
    on = experiment.gate_of("stale", 2.0, 2.0, frame, torch.full_like(frame.color, 1.0), frame.color)
    off = experiment.gate_of("stale", 2.0, 2.0, frame, torch.full_like(frame.color, 4.0), frame.color)
    assert on.mean().item() < 0.05 and off.min().item() > 0.99
    assert experiment.gate_of("none", 0.0, 2.0, frame, frame.color, frame.color) == 1.0


def test_the_difference_gate_grows_with_the_low_bands_difference():
    frame = static_frame(size=16)
    output = torch.full_like(frame.color, 0.25)
    small = experiment.gate_of("difference", 0.02, 2.0, frame, output, torch.full_like(output, 0.26))
    large = experiment.gate_of("difference", 0.02, 2.0, frame, output, torch.full_like(output, 1.0))
    assert small.max().item() < 0.2 and large.min().item() > 0.99


def test_the_wrapper_refuses_what_it_cannot_correct():
    with pytest.raises(ValueError, match="needs a 1x fused model"):
        experiment.LowBandCorrected(build_method("wskpn"), "none", 2.0, 0.0)
    with pytest.raises(ValueError, match="gate must be one of"):
        experiment.LowBandCorrected(build_method("fused:fast"), "always", 2.0, 0.0)
    with pytest.raises(ValueError, match="must be > 0"):
        experiment.LowBandCorrected(build_method("fused:fast"), "stale", 2.0, 0.0)
    with pytest.raises(ValueError, match="GATE:SIGMA:THRESHOLD"):
        experiment.parse_variant("stale:2")


def test_the_wrapper_carries_the_models_state_and_a_closed_gate_gives_the_models_output():
    model = build_method("fused:fast").eval()
    wrapped = experiment.LowBandCorrected(model, "difference", 2.0, 1e9)  # a threshold no difference reaches
    frames = [static_frame(size=16, seed=seed) for seed in range(3)]
    state = wrapped_state = None
    with torch.no_grad():
        for frame in frames:
            output, state = model.step(frame, state)
            corrected, wrapped_state = wrapped.step(frame, wrapped_state)
            torch.testing.assert_close(corrected, output, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(wrapped_state["model"]["history"], state["history"])


def test_the_experiment_runs_on_a_dataset_and_refuses_bad_input(tmp_path):
    data = write_tiny_dataset(tmp_path / "tiny")
    result = subprocess.run([sys.executable, str(SCRIPT), "--data", str(data), "--split", "validation",
                             "--model", "fused-fast-x1", "--variant", "stale:2:0.5", "--threads", "1",
                             "--report", str(tmp_path / "report.json")], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "report.json").read_text())
    assert [entry["label"] for entry in report["methods"]] == ["fused:fast", "fused:fast+lowband(stale,2,0.5)",
                                                               "oidn-taa:fast", "oidn:high"]
    for arguments in (["--data", str(tmp_path / "none")], ["--data", str(data), "--variant", "stale:x:1"]):
        refused = subprocess.run([sys.executable, str(SCRIPT), *arguments], capture_output=True, text=True, cwd=ROOT)
        assert refused.returncode == 2 and "try_lowband_correction:" in refused.stderr
