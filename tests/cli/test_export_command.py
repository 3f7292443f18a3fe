"""`denoiser export`: writes the ONNX file, checks it against PyTorch, and refuses what cannot be exported."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("onnxruntime")

from model.training.checkpoint import save_checkpoint  # noqa: E402
from model.methods.registry import build_method  # noqa: E402
from cli.main import main  # noqa: E402


def test_export_writes_the_file_and_checks_it(tmp_path, capsys):
    torch.manual_seed(2)
    checkpoint = save_checkpoint(tmp_path / "wskpn.pt", method=build_method("wskpn:xs", 1))
    assert main(["export", str(checkpoint), "--out", str(tmp_path / "w.onnx"), "--size", "24x16"]) == 0
    out, err = capsys.readouterr()
    # A line on stderr as each stage starts, then every stage's seconds.
    started = [line.split(":")[1].strip() for line in err.splitlines() if line.endswith(" ...")]
    assert started == ["load", "prepare", "torch.export", "onnx", "optimize", "write", "check pytorch",
                       "check onnxruntime"]
    summary = next(line for line in err.splitlines() if "seconds per stage" in line)
    assert all(f"{stage} " in summary for stage in started) and " s in all (" in summary
    assert (tmp_path / "w.onnx").stat().st_size > 1000
    assert "wskpn:xs at scale 1, 24x16 in" in out and ": within" in out
    assert '"color": [\n      1,\n      3,\n      16,\n      24' in out


@pytest.mark.parametrize("args, words", [
    (["oidn:high"], "OIDN's native library"),
    (["wskpn:s"], "untrained weights"),
    (["nothing-here"], "no checkpoint file, pretrained model"),
])
def test_export_refusals_exit_2_with_the_reason(tmp_path, capsys, args, words):
    checkpoint = save_checkpoint(tmp_path / "wskpn.pt", method=build_method("wskpn:xs", 1))
    args = [str(checkpoint) if arg == "CKPT" else arg for arg in args]
    assert main(["export", *args, "--out", str(tmp_path / "x.onnx")]) == 2
    assert words in capsys.readouterr().err


def test_torchscript_is_not_offered(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["export", "--help"])
    assert exit_info.value.code == 0 and "--format {onnx}" in capsys.readouterr().out  # the one choice
    with pytest.raises(SystemExit) as exit_info:
        main(["export", "x.pt", "--format", "torchscript", "--out", "x.onnx"])
    assert exit_info.value.code == 2 and "invalid choice: 'torchscript'" in capsys.readouterr().err


def test_exporting_the_shipped_default_says_its_sample_mean_is_left_out(tmp_path, capsys):
    assert main(["export", "fused-balanced-x1", "--out", str(tmp_path / "f.onnx"), "--size", "16x16"]) == 0
    out = capsys.readouterr().out
    assert '"sample_mean": "not exported' in out and ": within" in out
