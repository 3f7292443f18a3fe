"""experiments/widen_fused.py writes a wider fused checkpoint that `--init-from` and `--method` load as is."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from model.training.checkpoint import load_checkpoint, save_checkpoint
from model.methods.registry import build_method

ROOT = Path(__file__).resolve().parents[2]


def widen(*arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "experiments" / "widen_fused.py"), *arguments],
                          capture_output=True, text=True)


def test_a_checkpoint_is_widened_with_its_method_and_settings(tmp_path):
    source = build_method("fused:fast", 2)
    source.set_mean_max_frames(8)
    save_checkpoint(tmp_path / "best.pt", method=source)
    result = widen(str(tmp_path / "best.pt"), "--width", "20", "--out", str(tmp_path / "wide.pt"))
    assert result.returncode == 0, result.stderr
    content = load_checkpoint(tmp_path / "wide.pt")
    assert content["method"] == source.config()
    wide = build_method("fused:fast", 2)
    wide.load_state_dict(content["model"])
    assert wide.net.width == 20 and wide.mean_max_frames == 8


def test_a_narrower_width_or_another_method_is_refused_with_a_message(tmp_path):
    save_checkpoint(tmp_path / "fused.pt", method=build_method("fused"))
    narrower = widen(str(tmp_path / "fused.pt"), "--width", "8", "--out", str(tmp_path / "out.pt"))
    assert narrower.returncode == 2 and "more than the model's 16 channels" in narrower.stderr
    save_checkpoint(tmp_path / "wskpn.pt", method=build_method("wskpn"))
    other = widen(str(tmp_path / "wskpn.pt"), "--width", "24", "--out", str(tmp_path / "out.pt"))
    assert other.returncode == 2 and "not a fused model" in other.stderr
    missing = widen(str(tmp_path / "none.pt"), "--width", "24", "--out", str(tmp_path / "out.pt"))
    assert missing.returncode == 2 and "does not exist" in missing.stderr
    assert not (tmp_path / "out.pt").exists()
