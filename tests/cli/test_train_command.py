"""`denoiser train`: a tiny run end to end, resume and its refusal, and bad input exiting 2 with a clear message."""

from __future__ import annotations

import pytest

from model.training.checkpoint import load_checkpoint, load_method
from cli.main import main
from tests.builders import write_tiny_dataset
from tests.model.training_fixtures import TINY_METHOD


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("cli") / "data")


def tiny_args(data, out, *extra, steps: int = 2) -> list[str]:
    return ["train", "--data", str(data), "--method", TINY_METHOD, "--steps", str(steps), "--crop", "8",
            "--frames-per-sample", "2", "--batch", "2", "--warmup", "0", "--out", str(out), "--no-tracking",
            "--quiet", "--device", "cpu", *extra]


def test_train_runs_resumes_and_refuses_to_redo_a_finished_run(data, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # nothing may appear here but --out
    out = tmp_path / "run"
    assert main(tiny_args(data, out)) == 0
    printed = capsys.readouterr().out
    assert "trained 2 steps" in printed and str(out / "last.pt") in printed and "validation: psnr" in printed
    assert load_checkpoint(out / "last.pt")["step"] == 2
    assert load_method(out / "last.pt").name == TINY_METHOD

    assert main(tiny_args(data, out)) == 2
    assert "already at step 2 of 2" in capsys.readouterr().err
    # More steps continue the run from step 2.
    assert main(tiny_args(data, out, steps=3)) == 0
    captured = capsys.readouterr()
    assert "resuming from" in captured.err and "at step 2" in captured.err
    assert load_checkpoint(out / "last.pt")["step"] == 3
    assert main(tiny_args(data, out, "--no-resume")) == 0
    assert [path.name for path in tmp_path.iterdir()] == ["run"]


def test_sequences_too_short_for_a_sample_are_named_and_not_trained_on(data, tmp_path, capsys, monkeypatch):
    from model.training.train import train
    from model.training.training_settings import TrainConfig

    monkeypatch.chdir(tmp_path)
    # alpha's longest run without a cut is 3 frames (6 frames, a cut at 3): 4 frames per sample leave it out.
    assert main(tiny_args(data, tmp_path / "run", "--frames-per-sample", "4", steps=1)) == 0
    err = capsys.readouterr().err
    assert "note: 1 of 2 sequences of split 'train' hold fewer than 4 consecutive frames" in err and "alpha (3)" in err
    result = train(TrainConfig(data=str(data), method=TINY_METHOD, steps=1, crop=8, frames_per_sample=4, batch=2,
                               warmup_steps=0, out=str(tmp_path / "api-run"), device="cpu"))
    assert result["unused_sequences"] == [{"name": "alpha", "longest_run": 3}]
    # With samples every sequence can give, nothing is said.
    assert main(tiny_args(data, tmp_path / "run3", "--frames-per-sample", "3", steps=1)) == 0
    assert "note:" not in capsys.readouterr().err


@pytest.mark.parametrize("extra, message", [
    (["--method", "nope"], "unknown method 'nope'"),
    (["--data", "/nonexistent/data"], "/nonexistent/data"),
    (["--crop", "64"], "smaller than the 64x64 crop"),
    (["--batch", "3", "--world-size", "2"], "does not split evenly over 2 ranks"),
    (["--frames-per-sample", "9"], "9 consecutive frames"),
    (["--scale", "2", "--method", f"{TINY_METHOD}"], "does not run at scale 2"),
])
def test_bad_input_exits_2_with_a_message(data, tmp_path, capsys, extra, message):
    assert main(tiny_args(data, tmp_path / "bad", *extra)) == 2
    err = capsys.readouterr().err
    assert err.startswith("denoiser train: error:") and message in err


@pytest.mark.parametrize("extra", [["--lr", "0"], ["--lr", "nan"], ["--warmup", "-1"], ["--epochs", "1"],
                                   ["--device", "tpu"], ["--register-as", "auto"]])
def test_bad_options_are_refused_by_the_parser(data, tmp_path, extra):
    with pytest.raises(SystemExit) as exit_info:
        main(tiny_args(data, tmp_path / "bad", *extra))
    assert exit_info.value.code == 2


def test_the_name_auto_is_refused_with_the_reason(data, tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(tiny_args(data, tmp_path / "bad", "--register-as", "auto"))
    assert "'auto' is reserved" in capsys.readouterr().err


def test_help_lists_the_options(capsys):
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    text = capsys.readouterr().out
    for option in ("--data", "--method", "--scale", "--steps", "--crop", "--frames-per-sample", "--batch", "--lr",
                   "--out", "--world-size", "--device", "--tracking-uri", "--register-as", "--resume", "--no-resume",
                   "--seed"):
        assert option in text
