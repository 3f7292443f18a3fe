"""Every command finds the service's data folder, registry, tracking store and pretrained models through the
settings, whatever the current folder, and leaves nothing in it but the output it was asked for."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from cli.main import main
from core.settings import get_settings
from tests.builders import ship_tiny, write_gradient_dataset, write_tiny_dataset
from tests.model.training_fixtures import TINY_METHOD

REPOSITORY = Path(__file__).resolve().parents[2]
MODEL = "wskpn-xs-x1"  # the tiny shipped model, registered with the alias 'pretrained'


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """A data folder whose registry holds the tiny shipped model (registered by `denoiser pretrained --register`
    run from another folder), its pretrained folder, and a tiny dataset."""
    root = tmp_path_factory.mktemp("service")
    ship_tiny(root / "pretrained", name=MODEL)
    folders = {"DENOISER_DATA_DIR": root / "data", "DENOISER_PRETRAINED_DIR": root / "pretrained"}
    with pytest.MonkeyPatch.context() as patch:
        for name, value in folders.items():
            patch.setenv(name, str(value))
        patch.chdir(tmp_path_factory.mktemp("registering"))
        get_settings.cache_clear()
        try:
            assert main(["pretrained", "--register"]) == 0
        finally:
            get_settings.cache_clear()
    return {"env": folders, "dataset": write_gradient_dataset(root / "dataset", scales=(1,)),
            "training_data": write_tiny_dataset(root / "training-data")}


@pytest.fixture
def elsewhere(service, tmp_path, monkeypatch):
    """An empty current folder outside the checkout, with the settings pointing at the service's folders."""
    for name, value in service["env"].items():
        monkeypatch.setenv(name, str(value))
    get_settings.cache_clear()
    folder = tmp_path / "elsewhere"
    folder.mkdir()
    monkeypatch.chdir(folder)
    return folder


def entries(folder: Path) -> list[str]:
    return sorted(path.name for path in folder.iterdir())


def test_export_of_a_registered_model_from_an_empty_folder(service, tmp_path):
    folder = tmp_path / "empty"
    folder.mkdir()
    # A process of its own: nothing of this test's settings or current folder carries over.
    environment = {name: value for name, value in os.environ.items() if not name.startswith("DENOISER_")}
    environment.update({name: str(value) for name, value in service["env"].items()}, PYTHONPATH=str(REPOSITORY))
    result = subprocess.run([sys.executable, "-m", "cli.main", "export", f"models:/{MODEL}@pretrained",
                             "--format", "onnx", "--out", "x.onnx", "--size", "16"],
                            cwd=folder, env=environment, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "wrote x.onnx" in result.stdout and "within" in result.stdout
    assert entries(folder) == ["x.onnx"]


def test_evaluate_takes_registered_and_pretrained_models_from_anywhere(service, elsewhere, capsys):
    argv = ["evaluate", "--data", str(service["dataset"]), "--method", f"models:/{MODEL}@pretrained",
            "--model", f"models:/{MODEL}/1", "--method", MODEL, "--no-vdp", "--no-oidn", "--frames", "3",
            "--quiet", "--out", "report.json"]
    assert main(argv) == 0
    report = json.loads((elsewhere / "report.json").read_text())
    assert [entry["source"] for entry in report["methods"]] == [f"models:/{MODEL}@pretrained", f"models:/{MODEL}/1",
                                                               f"pretrained:{MODEL}"]
    # The same weights, found three ways: the same scores.
    assert len({entry["metrics"]["psnr"] for entry in report["methods"]}) == 1
    assert f"models:/{MODEL}@pretrained" in capsys.readouterr().out
    assert entries(elsewhere) == ["report.json"]


def test_compare_takes_a_registered_model(service, elsewhere, capsys):
    argv = ["compare", "--data", str(service["dataset"]), "--sequence", "a", "--method",
            f"models:/{MODEL}@pretrained=registered", "--method", MODEL, "--out", "frame.png"]
    assert main(argv) == 0
    assert "registered: PSNR" in capsys.readouterr().out
    assert entries(elsewhere) == ["frame.png"]


def test_benchmark_includes_registered_and_pretrained_models(service, elsewhere):
    argv = ["benchmark", "--data", str(service["dataset"]), "--scale", "1", "--method", "identity",
            "--include-learned", f"models:/{MODEL}@pretrained", MODEL, "--no-oidn-timing", "--frames", "3",
            "--quiet", "--out", "bench"]
    assert main(argv) == 0
    rows = json.loads((elsewhere / "bench" / "benchmark.json").read_text())["rows"]
    assert {row["source"] for row in rows} == {"identity:default", f"models:/{MODEL}@pretrained", MODEL}
    assert entries(elsewhere) == ["bench"]


@pytest.mark.parametrize("reference, message", [
    (f"models:/{MODEL}@champion", f"model '{MODEL}' has no alias 'champion'"),
    ("models:/no-such-model/1", "does not exist"),
])
def test_an_unknown_reference_exits_2_naming_it_and_leaves_nothing(service, elsewhere, capsys, reference, message):
    argv = ["evaluate", "--data", str(service["dataset"]), "--method", reference, "--no-vdp", "--no-oidn",
            "--out", "report.json"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert reference in err and message in err
    assert entries(elsewhere) == []


def test_train_without_out_writes_and_registers_in_the_data_folder(service, elsewhere, capsys):
    from core.registry import get_registry

    name = "tiny-anywhere"
    argv = ["train", "--data", str(service["training_data"]), "--method", TINY_METHOD, "--steps", "1", "--crop", "8",
            "--frames-per-sample", "2", "--batch", "2", "--warmup", "0", "--validate-every", "0", "--quiet",
            "--device", "cpu", "--register-as", name]
    assert main(argv) == 0
    assert f"registered model: {name} version 1" in capsys.readouterr().out
    runs = Path(service["env"]["DENOISER_DATA_DIR"]) / "runs" / TINY_METHOD
    assert (runs / "last.pt").is_file()
    assert get_registry().latest_version(name).version == "1"  # the store every command reads
    assert entries(elsewhere) == []
