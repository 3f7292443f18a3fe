"""`denoiser evaluate` and `denoiser methods`: a real run on a tiny dataset, JSON out, exit 2 for bad input."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from model.methods import registry
from model.methods.registry import MethodSpec
from cli.main import main
from tests.builders import NoisyInput, write_gradient_dataset

TEST_SPEC = MethodSpec(name="evaltest", description="noisy input, for the CLI tests",
                       factory=lambda preset, scale: NoisyInput(preset, scale), presets=("default",), scales=(1, 2))


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory) -> Path:
    return write_gradient_dataset(tmp_path_factory.mktemp("cli") / "data")


@pytest.fixture
def test_method(monkeypatch):
    registry._load_all()  # so that loading the real method modules later cannot overwrite the test entry
    monkeypatch.setitem(registry.REGISTRY, TEST_SPEC.name, TEST_SPEC)
    return TEST_SPEC.name


def test_evaluate_prints_a_table_and_writes_the_json_report(dataset_dir, tmp_path, test_method, capsys):
    out = tmp_path / "reports" / "eval.json"
    argv = ["evaluate", "--data", str(dataset_dir), "--method", test_method, "--method", f"{test_method}:default",
            "--out", str(out), "--frames", "3", "--threads", "1", "--no-vdp", "--no-oidn", "--quiet"]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "| method | params | FLOPs/px |" in printed and "1 threads" in printed and f"wrote {out}" in printed
    report = json.loads(out.read_text())
    assert [m["label"] for m in report["methods"]] == ["noisy_input", "noisy_input"]
    assert report["threads"] == 1 and report["timing_reference"] is None
    assert all(math.isfinite(m["metrics"]["psnr"]) and m["time_ratio_to_oidn"] is None for m in report["methods"])


@pytest.mark.skipif("oidn" not in {spec.name for spec in registry.all_methods()}, reason="OIDN method not built")
def test_evaluate_times_oidn_high_in_the_same_run(dataset_dir, tmp_path, capsys):
    out = tmp_path / "eval.json"
    argv = ["evaluate", "--data", str(dataset_dir), "--method", "identity", "--out", str(out), "--no-vdp", "--quiet"]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    assert report["timing_reference"]["label"] == "oidn:high" and report["timing_reference"]["ms_per_frame"] > 0
    assert report["methods"][0]["time_ratio_to_oidn"] > 0
    assert "oidn:high" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--method", "no_such_method"], "unknown method 'no_such_method'"),
    (["--method", "evaltest:huge"], "method 'evaltest' has no preset 'huge'"),
    (["--method", "checkpoints/missing.pt"], "checkpoint checkpoints/missing.pt not found"),
    (["--method", "evaltest", "--split", "train"], "no sequences in split 'train'"),
])
def test_bad_input_exits_2_with_a_message_naming_it(dataset_dir, test_method, argv, message, capsys):
    assert main(["evaluate", "--data", str(dataset_dir), "--no-vdp", "--no-oidn", "--quiet"] + argv) == 2
    assert message in capsys.readouterr().err


def test_missing_dataset_and_missing_scale_exit_2(tmp_path, test_method, capsys):
    assert main(["evaluate", "--data", str(tmp_path / "nowhere"), "--method", test_method, "--no-oidn"]) == 2
    assert str(tmp_path / "nowhere") in capsys.readouterr().err
    only_scale_one = write_gradient_dataset(tmp_path / "scale1", scales=(1,))
    argv = ["evaluate", "--data", str(only_scale_one), "--method", test_method, "--scale", "2", "--no-oidn"]
    assert main(argv) == 2
    assert "has no references at scale 2" in capsys.readouterr().err


def test_invalid_option_values_are_usage_errors(dataset_dir, capsys):
    for extra in (["--scale", "3"], ["--frames", "0"], ["--split", "holdout"], ["--device", "bogus"]):
        with pytest.raises(SystemExit) as exit_info:
            main(["evaluate", "--data", str(dataset_dir), "--method", "identity"] + extra)
        assert exit_info.value.code == 2
    assert "error" in capsys.readouterr().err


def test_methods_lists_every_method_and_preset_with_params_and_flops(monkeypatch, capsys):
    learned = MethodSpec(name="tinyconv", description="one 3x3 convolution", presets=("a", "b"), default_preset="b",
                         factory=lambda preset, scale: _TinyConv(preset, scale), learned=True)
    monkeypatch.setattr(registry, "all_methods", lambda: [TEST_SPEC, learned])
    assert main(["methods"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:5] == ["method", "scales", "learned", "params", "FLOPs/px"]
    rows = {line.split()[0]: line.split() for line in lines[1:] if not line.startswith("*")}
    assert set(rows) == {"evaltest", "tinyconv:a", "tinyconv:b"} and rows["tinyconv:b"][1] == "*"
    # 3 -> 3 channels, 3x3: 81 weights + 3 biases; 2 * 81 multiply-adds per pixel.
    assert rows["tinyconv:a"][2:5] == ["yes", "84", "162"]

    assert main(["methods", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [(row["method"], row["preset"]) for row in listed] == [("evaltest", "default"), ("tinyconv", "a"),
                                                                    ("tinyconv", "b")]


class _TinyConv(NoisyInput):
    name = "tinyconv"
    learned = True

    def __init__(self, preset: str = "default", scale: int = 1):
        super().__init__(preset, scale)
        import torch

        self.conv = torch.nn.Conv2d(3, 3, 3, padding=1)

    def step(self, frame, state):
        return self.conv(frame.color), {}


def test_compare_writes_a_picture_and_names_bad_input(dataset_dir, tmp_path, capsys):
    out = tmp_path / "cmp.png"
    assert main(["compare", "--data", str(dataset_dir), "--sequence", "a", "--scale", "2", "--method", "identity",
                 "--method", "accumulation=TA", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "TA: PSNR" in printed and out.is_file()
    assert main(["compare", "--data", str(dataset_dir), "--sequence", "zz", "--method", "identity",
                 "--out", str(out)]) == 2
    assert "has no sequence 'zz'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "--data", str(dataset_dir), "--sequence", "a", "--method", "identity", "--zoom", "1,2",
              "--out", str(out)])
    assert exit_info.value.code == 2


@pytest.mark.parametrize("command", ["evaluate", "compare"])
def test_a_device_that_is_not_there_is_refused_before_anything_runs(dataset_dir, tmp_path, command, capsys):
    argv = [command, "--data", str(dataset_dir), "--method", "identity", "--device", "cuda" if not
            torch.cuda.is_available() else "cuda:99"]
    argv += ["--sequence", "a", "--out", str(tmp_path / "c.png")] if command == "compare" else ["--no-oidn"]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "--device" in capsys.readouterr().err and not (tmp_path / "c.png").exists()


def test_compare_names_the_frame_asked_for(dataset_dir, tmp_path, capsys):
    assert main(["compare", "--data", str(dataset_dir), "--sequence", "a", "--frame", "-9", "--method", "identity",
                 "--out", str(tmp_path / "c.png")]) == 2
    assert "--frame -9: sequence 'a' has" in capsys.readouterr().err


def test_a_file_that_is_no_checkpoint_is_named_in_one_line(dataset_dir, tmp_path, capsys):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x89PNG not weights at all" * 20)
    assert main(["evaluate", "--data", str(dataset_dir), "--method", str(junk), "--no-oidn", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"{junk}: not a readable checkpoint: torch.load cannot read it as saved weights" in err
    assert len(err.strip().splitlines()) == 1 and "weights_only" not in err
