"""experiments/measure_unjittered_peers.py: the OIDN and OIDN + TAA peers with OIDN's estimate read at the pixel
centres, as the 1x fused models read it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from model.evaluation.evaluate import evaluate
from tests.builders import write_gradient_dataset, write_tiny_dataset

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "experiments" / "measure_unjittered_peers.py"
PEERS = [f"{name}:{quality}" for name in ("oidn", "oidn-taa") for quality in ("fast", "balanced", "high")]


def _measured(data: Path, split: str, out: Path) -> dict[str, float]:
    result = subprocess.run([sys.executable, str(SCRIPT), "--data", str(data), "--split", split, "--threads", "1",
                             "--no-vdp", "--out", str(out)], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    return {row["label"]: row["metrics"]["psnr"] for row in json.loads(out.read_text())["methods"]}


def _plain(data: Path, split: str) -> dict[str, float]:
    report = evaluate(data, PEERS, split, 1, threads=1, vdp=False, timing_reference=None)
    return {row["label"]: row["metrics"]["psnr"] for row in report["methods"]}


def test_frames_without_jitter_score_as_the_peers_do(tmp_path):
    data = write_gradient_dataset(tmp_path / "gradient", scales=(1,))  # every sample at the pixel centre
    measured, plain = _measured(data, "test", tmp_path / "report.json"), _plain(data, "test")
    assert set(measured) == set(plain) == set(PEERS)
    # the read at no shift is the image itself; only x / (1 + x) and back round the values
    assert all(abs(measured[peer] - plain[peer]) < 1e-3 for peer in PEERS), (measured, plain)


def test_jittered_frames_score_otherwise_and_a_missing_dataset_is_refused(tmp_path):
    data = write_tiny_dataset(tmp_path / "tiny")  # a random jitter per frame
    measured, plain = _measured(data, "validation", tmp_path / "report.json"), _plain(data, "validation")
    assert set(measured) == set(plain) == set(PEERS)
    assert all(abs(measured[peer] - plain[peer]) > 0.01 for peer in PEERS), (measured, plain)
    result = subprocess.run([sys.executable, str(SCRIPT), "--data", str(tmp_path / "none"), "--out",
                             str(tmp_path / "none.json")], capture_output=True, text=True, cwd=ROOT)
    assert result.returncode == 2 and "error:" in result.stderr and not (tmp_path / "none.json").exists()
