"""A Blender Cycles render, as Blender writes it, goes through import, training and evaluation without hand
conversion (the upload and the session with the raw files are tests/service/http/routes/test_dataset_layouts.py and
test_session_layouts.py)."""

from __future__ import annotations

from model.training.checkpoint import load_method
from model.io.dataset import Dataset
from cli.main import main
from tests.model.layouts.exr_builders import BLENDER_ORBIT
from tests.model.training_fixtures import TINY_METHOD


def test_import_then_train_and_evaluate_on_blender_frames(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    data = tmp_path / "data"
    for name, split in (("orbit_train", "train"), ("orbit_val", "validation")):
        assert main(["import", "--layout", "blender-cycles", str(BLENDER_ORBIT), "--out", str(data), "--name", name,
                     "--split", split]) == 0
    assert Dataset(data).names() == ["orbit_train", "orbit_val"]
    run = tmp_path / "run"
    assert main(["train", "--data", str(data), "--method", TINY_METHOD, "--steps", "2", "--crop", "16",
                 "--frames-per-sample", "2", "--batch", "1", "--warmup", "0", "--out", str(run), "--no-tracking",
                 "--quiet", "--device", "cpu"]) == 0
    assert "trained 2 steps" in capsys.readouterr().out
    assert load_method(run / "last.pt").name == TINY_METHOD
    assert main(["evaluate", "--data", str(data), "--split", "validation", "--method", str(run / "last.pt"),
                 "--no-vdp", "--out", str(tmp_path / "report.json")]) == 0
    assert (tmp_path / "report.json").is_file()
