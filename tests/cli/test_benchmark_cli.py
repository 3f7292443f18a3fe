"""`denoiser benchmark`: a real run at 1x and 2x on a tiny dataset (files, rows, charts), exit 2 for bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from model.training.checkpoint import save_checkpoint
from model.methods.registry import build_method
from cli.main import main
from tests.builders import write_gradient_dataset
from tests.model.training_fixtures import TINY_METHOD

FAST = ["--frames", "3", "--threads", "1", "--quiet", "--no-vdp"]


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory) -> Path:
    return write_gradient_dataset(tmp_path_factory.mktemp("bench") / "data")


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """A checkpoint of the test-only learned method, which runs at scale 1 only."""
    path = tmp_path_factory.mktemp("ckpt") / "tiny" / "best.pt"
    return save_checkpoint(path, method=build_method(TINY_METHOD), train_config={}, step=1)


def test_benchmark_at_both_scales_writes_tables_and_charts(dataset_dir, checkpoint, tmp_path, capsys):
    out = tmp_path / "bench"
    argv = ["benchmark", "--data", str(dataset_dir), "--method", "identity", "--method", "accumulation",
            "--include-learned", str(checkpoint), "--out", str(out), "--scale", "both", "--no-oidn-timing"] + FAST
    assert main(argv) == 0
    printed = capsys.readouterr().out
    for name in ("benchmark.json", "benchmark.md", "quality_speed.png", "quality_cost.png"):
        assert (out / name).stat().st_size > 0 and f"wrote {out / name}" in printed
    assert (out / "quality_speed.png").read_bytes()[:4] == b"\x89PNG"
    document = json.loads((out / "benchmark.json").read_text())
    assert document["scales"] == [1, 2] and set(document["reports"]) == {"1", "2"}
    rows = {(row["label"], row["scale"]) for row in document["rows"]}
    # The learned checkpoint runs at 1x only (its network depends on the scale) and is listed as not run at 2x.
    assert rows == {("identity", 1), ("accumulation", 1), (TINY_METHOD, 1), ("identity", 2), ("accumulation", 2)}
    assert document["skipped"] == [{"method": str(checkpoint), "scale": 2, "reason": document["skipped"][0]["reason"]}]
    learned = next(row for row in document["rows"] if row["label"] == TINY_METHOD)
    assert learned["source"] == str(checkpoint) and learned["learned"] and learned["params"] > 0
    assert all(row["ms_per_frame"] > 0 and row["psnr"] is not None for row in document["rows"])
    assert all(row["time_ratio_to_oidn"] is None for row in document["rows"])  # --no-oidn-timing
    assert document["reports"]["2"]["sequences"][0]["output_resolution"] == "32x32"
    assert document["threads"] == 1 and document["reports"]["1"]["frame_limit"] == 3
    assert "| accumulation | x2 |" in printed and f"- {checkpoint} at x2:" in printed


@pytest.mark.parametrize("argv, message", [
    (["--method", TINY_METHOD], f"'{TINY_METHOD}' is a learned method"),
    (["--method", "wskpn:s"], "--include-learned"),
    (["--method", "no_such_method"], "unknown method 'no_such_method'"),
    (["--method", "accumulation:huge"], "no preset 'huge'"),
    (["--method", "runs/x/best.pt"], "go to --include-learned"),
    (["--include-learned", "nowhere/best.pt"], "checkpoint not found"),
    (["--method", "identity", "--split", "train"], "no sequences in split 'train'"),
])
def test_bad_input_exits_2_with_a_message(dataset_dir, tmp_path, argv, message, capsys):
    base = ["benchmark", "--data", str(dataset_dir), "--out", str(tmp_path / "out"), "--no-oidn-timing"] + FAST
    assert main(base + argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # refused before anything ran


def test_missing_scale_and_wrong_scale_checkpoint_exit_2(dataset_dir, tmp_path, checkpoint, capsys):
    only_scale_one = write_gradient_dataset(tmp_path / "scale1", scales=(1,))
    base = ["benchmark", "--out", str(tmp_path / "out"), "--no-oidn-timing"] + FAST
    argv = ["--data", str(only_scale_one), "--method", "identity", "--scale", "both"]
    assert main(base + argv) == 2  # 'both' needs 2x references
    assert "has no references at scale 2" in capsys.readouterr().err
    argv = ["--data", str(dataset_dir), "--scale", "2", "--method", "identity", "--include-learned", str(checkpoint)]
    assert main(base + argv) == 2
    assert "cannot run at scale 2" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    (tmp_path / "file").write_text("")
    argv = ["benchmark", "--data", str(only_scale_one), "--scale", "1", "--out", str(tmp_path / "file")]
    assert main(argv) == 2 and "is a file" in capsys.readouterr().err


def test_invalid_option_values_and_help(dataset_dir, capsys):
    for extra in (["--scale", "3"], ["--threads", "0"], ["--split", "holdout"], ["--methods"], []):
        argv = ["benchmark", "--data", str(dataset_dir)] + extra  # [] lacks the required --out
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
    assert "error" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["benchmark", "--help"])
    text = capsys.readouterr().out
    assert exit_info.value.code == 0
    assert "Learned methods" in text and "untrained" in text and "--include-learned" in text
