"""experiments/measure_rejection_oracle.py: where the references changed, the oracle's composite, and the
measurement end to end on a tiny dataset."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from model.training.checkpoint import save_checkpoint
from model.methods.registry import build_method
from tests.builders import load_script, write_gradient_dataset

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "experiments" / "measure_rejection_oracle.py"
oracle = load_script("measure_rejection_oracle", "experiments")


def test_the_change_is_none_where_nothing_changed_a_third_where_light_doubled_and_all_after_a_cut():
    still = torch.full((1, 3, 8, 8), 2.0)
    doubled = still.clone()
    doubled[..., :, 4:] = 4.0  # the right half doubles: |4 - 2| / (4 + 2 + 0.02)
    references = torch.cat([still, still, doubled, still])
    change = oracle.changed_share(references, [False, False, False, True])
    assert torch.all(change[:2] == 0) and torch.all(change[3] == 1)
    # away from the edge between the halves, where the 5 x 5 mean mixes them
    torch.testing.assert_close(change[2, 0, :, 7], torch.full((8,), 2.0 / 6.02))
    torch.testing.assert_close(change[2, 0, :, 0], torch.zeros(8))


def test_the_oracle_takes_the_estimate_exactly_past_the_threshold():
    output, estimate = torch.zeros(2, 3, 4, 4), torch.ones(2, 3, 4, 4)
    change = torch.tensor([0.01, 0.2]).view(2, 1, 1, 1).expand(2, 1, 4, 4)
    composite = oracle.oracle(output, estimate, change, 0.1)
    assert torch.all(composite[0] == 0) and torch.all(composite[1] == 1)


def test_the_measurement_runs_on_a_dataset_its_extremes_are_the_model_and_the_estimate(tmp_path):
    data = write_gradient_dataset(tmp_path / "data", scales=(1,))
    model = save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast"))
    out = tmp_path / "oracle.json"
    result = subprocess.run([sys.executable, str(SCRIPT), "--data", str(data), "--model", str(model), "--no-vdp",
                             "--threads", "1", "--threshold", "-1", "--threshold", "2", "--out", str(out)],
                            capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    rows = json.loads(out.read_text())["rows"]
    assert [row["sequence"] for row in rows] == ["a", "b"]
    for row in rows:
        everywhere, nowhere = row["oracle"]
        assert everywhere["share"] == 1.0 and nowhere["share"] == 0.0
        assert everywhere["psnr"] == pytest.approx(row["estimate_scores"]["psnr"])
        assert nowhere["psnr"] == pytest.approx(row["model_scores"]["psnr"])
        assert row["model_scores"]["fvvdp_jod"] is None
    assert "| a | " in out.with_suffix(".md").read_text()


@pytest.mark.parametrize(("arguments", "message"), [(["--sequence", "zeta"], "no sequence zeta"),
                                                    (["--model", "wskpn:xs"], "needs a 1x fused model")])
def test_what_it_cannot_measure_is_refused(tmp_path, arguments, message):
    data = write_gradient_dataset(tmp_path / "data", scales=(1,))
    model_arguments = [] if "--model" in arguments else ["--model", "fused:fast"]
    refused = subprocess.run([sys.executable, str(SCRIPT), "--data", str(data), "--no-vdp", *model_arguments,
                              *arguments], capture_output=True, text=True, cwd=ROOT)
    assert refused.returncode == 2 and message in refused.stderr
