"""MLflow tracking against a temporary SQLite store: params, metrics, sample grids, the registered model, resume."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model.training.checkpoint import load_checkpoint, load_method
from model.training.train import TrainConfig, train
from tests.builders import write_tiny_dataset
from tests.model.training_fixtures import TINY_METHOD
from core.tracking import (
    MLflowTracker,
    download_registered_checkpoint,
    resolve_tracking_uri,
    save_image_grid,
    sqlite_path,
)


class Interrupted(Exception):
    pass


def config_for(tmp_path, **changes) -> TrainConfig:
    values = dict(method=TINY_METHOD, data=str(tmp_path / "data"), crop=8, frames_per_sample=2, batch=2,
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
    # The model was logged inside the run (one of its outputs) and its measurements are the run's metrics too.
    [output] = run.outputs.model_outputs
    assert client.get_logged_model(output.model_id).source_run_id == run.info.run_id
    assert run.data.metrics["validation_psnr"] == pytest.approx(result["validation"]["psnr"], abs=1e-4)
    assert version.description.startswith(f"{TINY_METHOD}:default at scale 1 ({result['parameters']} parameters")

    # Lineage: the code version and the dataset, by its manifests' digest.
    from model.io.dataset import dataset_digest

    assert run.data.tags["code_version"] and run.data.tags["code_version"] != "unknown"
    inputs = run.inputs.dataset_inputs
    assert [(i.dataset.name, i.dataset.digest, i.tags[0].value) for i in inputs] == \
        [("data", dataset_digest(tmp_path / "data")[:36], "training")]

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


def test_tracking_uri_is_the_settings_one_whatever_the_current_folder(monkeypatch, tmp_path):
    from core.settings import get_settings

    monkeypatch.delenv("DENOISER_TRACKING_URI", raising=False)
    monkeypatch.setenv("DENOISER_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path / "..")
    get_settings.cache_clear()
    try:
        assert resolve_tracking_uri(None) == f"sqlite:///{tmp_path / 'data' / 'mlflow' / 'mlflow.db'}"
        monkeypatch.setenv("DENOISER_TRACKING_URI", "postgresql://mlflow@db/mlflow")
        get_settings.cache_clear()
        assert resolve_tracking_uri(None) == "postgresql://mlflow@db/mlflow"
    finally:
        get_settings.cache_clear()
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


def registered_wskpn(tmp_path, uri: str, name: str, seed: int):
    """A seeded wskpn:xs checkpoint logged from a run and registered as version 1 of ``name``, alias champion."""
    from model.methods.registry import build_method
    from model.training.checkpoint import save_checkpoint

    torch.manual_seed(seed)
    checkpoint = save_checkpoint(tmp_path / "wskpn.pt", method=build_method("wskpn:xs", 1))
    tracker = MLflowTracker(uri, "tests")
    tracker.start({"method": "wskpn:xs"})
    tracker.log_model(checkpoint, name, {"method": "wskpn"})
    tracker.finish("FINISHED")
    tracker.client.set_registered_model_alias(name, "champion", "1")
    return checkpoint


def sequence_arrays(frames):
    """FrameBundles as the pyfunc model's input: named (T, H, W, C) arrays and the jitter."""
    names = ("color", "albedo", "normal", "depth", "motion", "diffuse", "specular", "specular_albedo", "roughness")
    arrays = {name: np.stack([getattr(frame, name) for frame in frames]).astype(np.float32) for name in names
              if all(getattr(frame, name) is not None for frame in frames)}
    arrays = {name: array[..., None] if array.ndim == 3 else array for name, array in arrays.items()}  # depth
    arrays["jitter"] = np.array([frame.jitter for frame in frames], dtype=np.float32)
    return arrays


def test_a_registered_model_loads_through_mlflow_pyfunc_and_denoises_a_sequence(tmp_path, monkeypatch):
    import dataclasses

    import mlflow

    from model.methods.base import FrameBatch
    from tests.builders import synthetic_frame

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    checkpoint = registered_wskpn(tmp_path, uri, "wskpn-pyfunc", seed=5)

    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("MLFLOW_REGISTRY_URI", uri)
    model = mlflow.pyfunc.load_model("models:/wskpn-pyfunc@champion")
    assert [spec.name for spec in model.metadata.get_input_schema().inputs] == \
        ["color", "albedo", "normal", "depth", "motion", "jitter"]
    rng = np.random.default_rng(0)
    # The signature's buffers only (MLflow drops undeclared inputs; module notes of core.pyfunc_model).
    frames = [dataclasses.replace(synthetic_frame(rng, index, 16, 16), diffuse=None, specular=None,
                                  specular_albedo=None, roughness=None) for index in range(4)]
    output = model.predict(sequence_arrays(frames))
    assert output.shape == (4, 16, 16, 3) and output.dtype == np.float32

    # The same as stepping the checkpoint in process, history carried over the sequence.
    method, state = load_method(checkpoint).for_inference(), None
    with torch.no_grad():
        for index, frame in enumerate(frames):
            expected, state = method.step(FrameBatch.from_bundles([frame], scale=None), state)
            np.testing.assert_allclose(output[index], expected[0].permute(1, 2, 0).numpy(), rtol=1e-5, atol=1e-6)
    # History matters: frame 3 alone (a new sequence) gives another output than frame 3 after 0-2.
    alone = model.predict(sequence_arrays(frames[3:]))
    assert not np.allclose(alone[0], output[3])
    with pytest.raises(Exception, match="jitter"):
        model.predict({key: value for key, value in sequence_arrays(frames).items() if key != "jitter"})
    # The optional buffers reach the model through the unwrapped python model.
    full = [synthetic_frame(np.random.default_rng(1), index, 16, 16) for index in range(2)]
    direct = model.unwrap_python_model().predict(None, sequence_arrays(full))
    method, state = load_method(checkpoint).for_inference(), None
    with torch.no_grad():
        for index, frame in enumerate(full):
            expected, state = method.step(FrameBatch.from_bundles([frame], scale=None), state)
            np.testing.assert_allclose(direct[index], expected[0].permute(1, 2, 0).numpy(), rtol=1e-5, atol=1e-6)


# Run with -I in a bare folder: our packages may come only from the downloaded model's code folder, never from
# the checkout or the venv's editable install (a finder on sys.meta_path that this blocker runs before).
ISOLATED_PROBE = """
import importlib.machinery, json, sys
folder, checkout = sys.argv[1], sys.argv[2]
OURS = {"core", "service", "workers", "cli", "client", "model", "tests"}

class OnlyTheModelsCode:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] not in OURS:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path)
        if spec is None or not str(spec.origin).startswith(folder):
            raise ImportError(f"blocked: {name} from {spec.origin if spec else 'nowhere'}")
        return spec

sys.meta_path.insert(0, OnlyTheModelsCode())
assert checkout not in [entry.rstrip("/") for entry in sys.path], sys.path
import mlflow
import numpy as np

model = mlflow.pyfunc.load_model("models:/isolated@champion", dst_path=folder)
np.save("output.npy", model.predict(dict(np.load("inputs.npz"))))
print(json.dumps(sorted(name for name in sys.modules if name.split(".")[0] in OURS)))
print(json.dumps(sorted({getattr(module, "__file__", None) or "" for name, module in sys.modules.items()
                         if name.split(".")[0] in OURS})))
"""


def test_a_logged_model_loads_and_predicts_in_a_python_without_the_project(tmp_path):
    import json
    import os
    import subprocess
    import sys
    from pathlib import Path

    from tests.builders import synthetic_frame
    from core.pyfunc_model import REQUIRED, denoise_sequence

    checkout = str(Path(__file__).resolve().parents[2])
    uri = f"sqlite:///{tmp_path / 'registry' / 'mlflow.db'}"
    checkpoint = registered_wskpn(tmp_path, uri, "isolated", seed=11)

    rng = np.random.default_rng(2)
    frames = [synthetic_frame(rng, index, 16, 16) for index in range(2)]
    inputs = {name: array for name, array in sequence_arrays(frames).items() if name in (*REQUIRED, "jitter")}
    work = tmp_path / "elsewhere"
    (work / "download").mkdir(parents=True)
    np.savez(work / "inputs.npz", **inputs)
    env = {"PATH": os.environ.get("PATH", ""), "HOME": str(work), "MLFLOW_TRACKING_URI": uri,
           "MLFLOW_REGISTRY_URI": uri, "MLFLOW_DISABLE_TELEMETRY": "true"}
    result = subprocess.run([sys.executable, "-I", "-c", ISOLATED_PROBE, str(work / "download"), checkout],
                            cwd=work, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    modules, files = (json.loads(line) for line in result.stdout.strip().splitlines()[-2:])
    assert "model.training.checkpoint" in modules and not any(name.split(".")[0] == "core" for name in modules)
    assert files and all(path.startswith(str(work / "download")) for path in files), files

    # The same frames stepped in this process give the same RGB.
    expected = denoise_sequence(load_method(checkpoint).for_inference(), inputs)
    output = np.load(work / "output.npy")
    assert output.shape == (2, 16, 16, 3)
    np.testing.assert_allclose(output, expected, rtol=1e-5, atol=1e-6)


def test_a_fused_run_logs_the_run_time_settings_its_model_runs(tmp_path):
    write_tiny_dataset(tmp_path / "data")
    uri = f"sqlite:///{tmp_path / 'tracking' / 'mlflow.db'}"
    config = config_for(tmp_path, tracking_uri=uri, method="fused:fast", scale=2, steps=1, validate_every=0,
                        register_as="tiny-fused")
    tracker = MLflowTracker(uri, config.experiment)
    train(config, tracker=tracker)
    params = tracker.client.get_run(tracker.run_id).data.params
    assert params["shipped_settings"] == "True"
    assert (params["setting.albedo_detail_frames"], params["setting.stale_test_sigmas"],
            params["setting.history_before_kernel"]) == ("8", "1.0", "False")
    plain = MLflowTracker(uri, config.experiment)
    train(config_for(tmp_path, tracking_uri=uri, steps=1, validate_every=0, out=str(tmp_path / "plain")),
          tracker=plain)
    assert not any(name.startswith("setting.") for name in plain.client.get_run(plain.run_id).data.params)
