"""MLflow tracking against a temporary SQLite store: params, metrics, sample grids, the registered model, resume."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model.checkpoint import load_checkpoint, load_method
from model.train import TrainConfig, train
from tests.model.training_fixtures import TINY_METHOD, write_tiny_dataset
from workers.tracking import (
    MLflowTracker,
    default_tracking_uri,
    download_registered_checkpoint,
    resolve_tracking_uri,
    save_image_grid,
    sqlite_path,
)


class Interrupted(Exception):
    pass


def config_for(tmp_path, **changes) -> TrainConfig:
    values = dict(method=TINY_METHOD, data=str(tmp_path / "data"), crop_size=8, frames_per_sample=2, batch_size=2,
                  steps=3, warmup_steps=0, out=str(tmp_path / "out"), checkpoint_every=1, validate_every=2,
                  register_as="tiny-denoiser", experiment="tests")
    values.update(changes)
    return TrainConfig(**values)


def test_a_training_run_is_tracked_and_its_model_registered(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # so a call that fell back on MLflow's default store would show up here
    write_tiny_dataset(tmp_path / "data")
    uri = f"sqlite:///{tmp_path / 'tracking' / 'mlflow.db'}"
    config = config_for(tmp_path, tracking_uri=uri)

    def stop_after_two(step, total, message):
        if step == 2:
            raise Interrupted

    # Interrupted after step 2 (checkpointed), then resumed: one run holds the whole history.
    first = MLflowTracker(uri, config.experiment)
    with pytest.raises(Interrupted):
        train(config, tracker=first, progress=stop_after_two)
    client = first.client
    assert client.get_run(first.run_id).info.status == "FAILED"
    tracker = MLflowTracker(uri, config.experiment)
    result = train(config, tracker=tracker)
    assert tracker.run_id == first.run_id == result["run_id"]

    run = client.get_run(tracker.run_id)
    assert run.info.status == "FINISHED"
    params = run.data.params
    assert params["method"] == TINY_METHOD and params["lr"] == "0.001" and params["steps"] == "3"
    assert params["parameters"] == str(result["parameters"]) and float(params["flops_per_pixel"]) > 0
    losses = client.get_metric_history(run.info.run_id, "train/loss")
    assert [m.step for m in losses] == [1, 2, 3]
    assert all(np.isfinite(m.value) for m in losses)
    validation = client.get_metric_history(run.info.run_id, "validation/psnr")
    assert [m.step for m in validation] == [2, 3]
    assert validation[-1].value == pytest.approx(result["validation"]["psnr"])
    samples = [a.path for a in client.list_artifacts(run.info.run_id, "samples")]
    assert samples == ["samples/step_0000002.png", "samples/step_0000003.png"]

    # Artifacts live next to the database; nothing went to MLflow's defaults in the current folder.
    assert (tmp_path / "tracking" / "artifacts" / "tests").is_dir()
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "mlruns").exists()

    registered = result["registered_model"]
    assert registered["name"] == "tiny-denoiser" and registered["version"] == "1"
    version = client.get_model_version("tiny-denoiser", "1")
    assert version.run_id == run.info.run_id
    assert version.tags["method"] == TINY_METHOD and version.tags["preset"] == "default"
    assert version.tags["scale"] == "1" and version.tags["params"] == str(result["parameters"])
    assert float(version.tags["flops_per_pixel"]) == pytest.approx(result["flops_per_pixel"], rel=1e-5)
    assert float(version.tags["validation_psnr"]) == pytest.approx(result["validation"]["psnr"], abs=1e-4)

    # The registered checkpoint loads back into the trained method.
    downloaded = download_registered_checkpoint("tiny-denoiser", 1, tmp_path / "download", tracking_uri=uri)
    method = load_method(downloaded)
    final = load_checkpoint(result["checkpoint"])["model"]
    for name, tensor in method.state_dict().items():
        assert torch.equal(tensor, final[name])


def test_image_grid_is_a_png_with_a_panel_per_image(tmp_path):
    rng = np.random.default_rng(0)
    columns = {name: [rng.uniform(0, 1, (8, 8, 3)) for _ in range(2)] for name in ("noisy", "output", "reference")}
    path = save_image_grid(columns, tmp_path / "grid.png", title="step 1")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image

    height, width = matplotlib.image.imread(path).shape[:2]
    assert width > height  # three columns, two rows
    with pytest.raises(ValueError, match="at least one column"):
        save_image_grid({}, tmp_path / "empty.png")


def test_tracking_uri_is_one_setting(monkeypatch, tmp_path):
    monkeypatch.delenv("DENOISER_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    assert resolve_tracking_uri(None) == default_tracking_uri() == f"sqlite:///{tmp_path / 'mlruns' / 'mlflow.db'}"
    monkeypatch.setenv("DENOISER_TRACKING_URI", "postgresql://mlflow@db/mlflow")
    assert resolve_tracking_uri(None) == "postgresql://mlflow@db/mlflow"
    assert resolve_tracking_uri("sqlite:////x/y.db") == "sqlite:////x/y.db"
    assert sqlite_path("sqlite:////x/y.db").as_posix() == "/x/y.db" and sqlite_path("http://host:5000") is None


def test_two_trackers_starting_together_on_a_new_database_both_work(tmp_path):
    # Two training jobs started at once on a fresh SQLite file raced in MLflow's table creation.
    import multiprocessing

    uri = f"sqlite:///{tmp_path / 'fresh' / 'mlflow.db'}"
    context = multiprocessing.get_context("spawn")
    with context.Pool(2) as pool:
        run_ids = pool.map(_start_a_run, [(uri, "a"), (uri, "b")])
    assert len(set(run_ids)) == 2


def _start_a_run(arguments):
    uri, name = arguments
    tracker = MLflowTracker(uri, experiment="race")
    tracker.start({"method": name})
    tracker.finish("FINISHED")
    return tracker.run_id
