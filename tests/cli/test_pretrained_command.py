"""`denoiser pretrained`: the listing with held-out scores, idempotent registration with the alias, damaged files."""

from __future__ import annotations

import pytest

import model.deployment.pretrained as pretrained
from cli.main import main
from tests.builders import report_for, ship_tiny


@pytest.fixture
def shipped(tmp_path, monkeypatch):
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    return ship_tiny(tmp_path / "pretrained", report=report_for())


def test_the_listing_shows_held_out_scores_next_to_oidn(shipped, capsys):
    assert main(["pretrained"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:3] == ["name", "method", "scale"]
    row = lines[1].split()
    assert row[:5] == ["wskpn-xs-x1", "wskpn:xs", "1", str(shipped.manifest["params"]), "120"]
    assert row[5:10] == ["30.50", "0.1000", "31.00", "31.40", "(high)"] and row[-1] == "ok"


def test_a_fused_model_is_listed_beside_oidn_taa_at_its_own_quality(tmp_path, monkeypatch, capsys):
    from model.training.checkpoint import save_checkpoint
    from model.methods.registry import build_method
    from model.deployment.pretrained import ship_checkpoint

    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    report = report_for()
    own = report["methods"][0]
    own.update(label="fused:fast", method="fused", preset="fast")
    taa_fast = dict(report["methods"][2], label="oidn-taa:fast", source="oidn-taa:fast", preset="fast",
                    metrics={"psnr": 29.9, "flip": 0.1})
    report["methods"].append(taa_fast)
    source = save_checkpoint(tmp_path / "fused.pt", method=build_method("fused:fast", 1), step=30,
                             train_config={"steps": 30})
    ship_checkpoint(source, "fused-fast-x1", root=tmp_path / "pretrained", report=report,
                    report_source="runs/x/best.pt")
    assert main(["pretrained"]) == 0
    row = capsys.readouterr().out.splitlines()[1].split()
    assert row[0] == "fused-fast-x1" and row[7:10] == ["31.00", "29.90", "(fast)"]  # not OIDN + TAA-high's 31.40


def test_registration_is_idempotent_and_sets_the_alias(shipped, tmp_path, capsys):
    from mlflow import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert main(["pretrained", "--register", "--tracking-uri", uri]) == 0
    assert "wskpn-xs-x1: registered as version 1; models:/wskpn-xs-x1@pretrained" in capsys.readouterr().out
    assert main(["pretrained", "--register", "--tracking-uri", uri]) == 0
    assert "wskpn-xs-x1: already registered as version 1" in capsys.readouterr().out
    client = MlflowClient(uri, registry_uri=uri)
    versions = client.search_model_versions("name = 'wskpn-xs-x1'")
    assert [str(v.version) for v in versions] == ["1"]
    tags = versions[0].tags
    assert tags["sha256"] == shipped.sha256 and tags["method"] == "wskpn" and tags["pretrained"] == "true"
    assert float(tags["metric.held_out_psnr"]) == 30.5 and float(tags["metric.held_out_oidn_high_psnr"]) == 31.0
    assert str(client.get_model_version_by_alias("wskpn-xs-x1", "pretrained").version) == "1"
    # The held-out scores are metrics of the version's run, linked to its logged model, and the description tells
    # what it is, what it was trained on and its held-out table.
    version = client.get_model_version("wskpn-xs-x1", "1")
    run = client.get_run(version.run_id)
    assert {key: run.data.metrics[key] for key in ("held_out_psnr", "held_out_flip", "held_out_oidn_high_psnr")} \
        == {"held_out_psnr": 30.5, "held_out_flip": 0.1, "held_out_oidn_high_psnr": 31.0}
    [output] = run.outputs.model_outputs
    logged = client.get_logged_model(output.model_id)
    assert logged.source_run_id == version.run_id
    assert {metric.key: metric.value for metric in logged.metrics}["held_out_psnr"] == 30.5
    assert "wskpn:xs at scale 1" in version.description and "Trained 120 steps on `data/demo`" in version.description
    assert "| wskpn-xs-x1 | **wskpn:xs** (shipped) | 30.50 |" in version.description
    assert "| wskpn-xs-x1 | oidn:high | 31.00 |" in version.description
    assert "shipped with the project" in client.get_registered_model("wskpn-xs-x1").description
    # The registered checkpoint is the shipped file.
    from core.tracking import download_registered_checkpoint

    local = download_registered_checkpoint("wskpn-xs-x1", 1, tmp_path / "download", tracking_uri=uri)
    assert pretrained.file_sha256(local) == shipped.sha256
    # ... and the registered version is a pyfunc model with a signature.
    import mlflow

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("MLFLOW_TRACKING_URI", uri)
        patch.setenv("MLFLOW_REGISTRY_URI", uri)
        model = mlflow.pyfunc.load_model("models:/wskpn-xs-x1@pretrained")
    assert "jitter" in model.metadata.get_input_schema().input_names()


def test_a_version_registered_without_its_code_is_registered_again_once(shipped, tmp_path, capsys):
    from mlflow import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert main(["pretrained", "--register", "--tracking-uri", uri]) == 0
    client = MlflowClient(uri, registry_uri=uri)
    client.delete_model_version_tag("wskpn-xs-x1", "1", "pyfunc_layout")  # as registered before models had code
    assert main(["pretrained", "--register", "--tracking-uri", uri]) == 0
    assert main(["pretrained", "--register", "--tracking-uri", uri]) == 0
    out = capsys.readouterr().out
    assert "wskpn-xs-x1: registered as version 2;" in out and "already registered as version 2" in out
    assert str(client.get_model_version_by_alias("wskpn-xs-x1", "pretrained").version) == "2"
    assert len(client.search_model_versions("name = 'wskpn-xs-x1'")) == 2


def test_a_damaged_model_is_reported_and_exits_2(shipped, capsys):
    shipped.path.write_bytes(b"not a checkpoint")
    assert main(["pretrained"]) == 2
    captured = capsys.readouterr()
    assert "DAMAGED" in captured.out and "damaged or was replaced" in captured.out
    assert "1 pretrained model(s) fail their check" in captured.err


def test_the_markdown_table_puts_the_model_next_to_oidn_of_the_same_run(shipped, capsys):
    assert main(["pretrained", "--markdown"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].startswith("| wskpn-xs-x1 | **wskpn:xs** (shipped) | 30.50 |")
    assert [line.split(" | ")[1] for line in lines[3:]] == ["oidn:high", "oidn-taa:high"]


def test_a_pending_model_says_so_in_the_table(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    ship_tiny(tmp_path / "pretrained")
    assert main(["pretrained", "--markdown"]) == 0
    assert "| wskpn-xs-x1 | held-out evaluation pending |" in capsys.readouterr().out


def test_a_manifest_note_is_printed_under_the_listing_and_kept_in_the_registered_descriptions(shipped, tmp_path,
                                                                                              capsys):
    import json

    from mlflow import MlflowClient

    manifest_path = shipped.folder / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["note"] = "Not a faster model: see docs/results/int8.md."
    manifest_path.write_text(json.dumps(manifest))
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert main(["pretrained", "--register", "--tracking-uri", uri]) == 0
    assert "wskpn-xs-x1: Not a faster model: see docs/results/int8.md." in capsys.readouterr().out.splitlines()
    client = MlflowClient(uri, registry_uri=uri)
    assert "Not a faster model" in client.get_model_version("wskpn-xs-x1", "1").description
    assert "Not a faster model" in client.get_registered_model("wskpn-xs-x1").description


def test_the_shipped_int8_model_says_it_is_not_faster():
    note = pretrained.get_pretrained("jnds-s-int8-x2").manifest["note"]
    assert "Not a faster model" in note and "docs/results/int8.md" in note
