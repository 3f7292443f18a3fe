"""Each job kind run in this process by workers.tasks.jobs.execute, against Redis db 15 and a tmp data folder."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import OpenEXR
import pytest
import torch

from model.io.dataset import Dataset
from model.methods.base import FrameBatch
from model.methods.registry import build_method
from core.jobs.kinds import JOB_PARAMS
from tests.builders import write_sequence
from tests.model.training_fixtures import TINY_METHOD
from tests.workers.tasks.datasets import store_dataset
from workers.tasks import generate as generate_module
from workers.tasks.context import JobCancelled, JobContext, Watchdog
from workers.tasks.jobs import execute
from core.errors import DomainError, Invalid, NotFound
from core.jobs.kinds import check
from workers.tasks.train import plugin_modules


@pytest.fixture
def dataset(storage):
    return store_dataset(storage)


def submit(store, storage, settings, kind: str, device: str = "cpu", **params) -> str:
    """What POST /jobs does, without HTTP: check the parameters, store the record."""
    checked = check(kind, JOB_PARAMS[kind].model_validate(params), storage, settings)
    return store.create(kind, checked, device, device)["id"]


def run(store, storage, settings, job_id: str, reports: list | None = None) -> dict:
    execute(job_id, store, storage, settings, sink=None if reports is None else reports.append)
    return store.require(job_id)


def train_params(**changes) -> dict:
    return {"dataset": "tiny", "method": TINY_METHOD, "steps": 3, "crop": 8, "batch": 2, "frames_per_sample": 2,
            "warmup_steps": 0, "validate_every": 0, "checkpoint_every": 1, "track": False, **changes}


# ------------------------------------------------------------------------------------------ evaluate

def test_evaluate_writes_reports_and_mirrors_progress(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "evaluate", dataset="tiny", methods=["identity", "accumulation"],
                    vdp=False, oidn_timing=False, track=False)
    reports = []
    record = run(store, storage, settings, job_id, reports)
    assert record["state"] == "succeeded", record["error"]
    assert record["attempts"] == 1 and record["finished_at"] and record["error"] is None
    result = record["result"]
    assert [m["source"] for m in result["methods"]] == ["identity", "accumulation"]
    assert result["sequences"] == 2 and result["frames"] == 8
    assert result["methods"][1]["metrics"]["psnr"] > result["methods"][0]["metrics"]["psnr"]
    assert "| accumulation |" in result["table"]
    report = json.loads((storage.job(job_id) / "report.json").read_text())
    assert report["dataset"] == "tiny" and len(report["methods"]) == 2
    assert result["artifacts"]["report.md"] == f"/jobs/{job_id}/artifacts/report.md"
    # Progress: 2 methods x 2 sequences, mirrored to the sink (Celery's update_state) in the fixed shape.
    assert record["progress"]["current"] == record["progress"]["total"] == 4
    assert reports and all(set(r) == {"current", "total", "message", "eta_seconds"} for r in reports)
    log = (storage.job(job_id) / "job.log").read_text()
    assert "attempt 1 of evaluate job" in log and "succeeded" in log


def test_a_tracked_evaluation_draws_and_logs_each_sequences_last_frame_side_by_side(store, storage, settings,
                                                                                     dataset):
    from mlflow.tracking import MlflowClient

    job_id = submit(store, storage, settings, "evaluate", dataset="tiny", methods=["identity", "accumulation"],
                    vdp=False, oidn_timing=False, track=True, frames=3)
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    pictures = {"comparison_delta.png", "comparison_epsilon.png"}  # the test split's two sequences
    assert pictures <= set(record["result"]["artifacts"])
    assert record["result"]["artifacts"]["comparison_delta.png"] == f"/jobs/{job_id}/artifacts/comparison_delta.png"
    for name in pictures:
        assert (storage.job(job_id) / name).read_bytes()[:4] == b"\x89PNG"
    client = MlflowClient(settings.resolved_tracking_uri())
    assert pictures <= {item.path for item in client.list_artifacts(record["mlflow_run_id"])}


def test_benchmark_defaults_to_baselines_and_oidn_and_draws_a_chart(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "benchmark", dataset="tiny", vdp=False, track=False, frames=3)
    # The defaults of `denoiser benchmark` too: every non-learned method, OIDN and OIDN + TAA at all three presets.
    assert store.get(job_id)["params"]["methods"] == ["accumulation", "identity", "oidn:fast", "oidn:balanced",
                                                      "oidn:high", "oidn-taa:fast", "oidn-taa:balanced",
                                                      "oidn-taa:high", "svgf"]
    store.update(job_id, params={**store.get(job_id)["params"], "methods": ["identity", "oidn:fast"]})
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    result = record["result"]
    assert result["timing_reference"]["label"] == "oidn:high" and result["methods"][1]["time_ratio_to_oidn"] > 0
    assert (storage.job(job_id) / "quality_speed.png").stat().st_size > 1000
    assert set(result["artifacts"]) == {"report.json", "report.md", "quality_speed.png", "benchmark.json",
                                        "benchmark.md", "quality_cost.png"}


def test_a_dataset_gone_before_the_run_fails_the_job_with_a_message(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "evaluate", dataset="tiny", methods=["identity"], vdp=False,
                    oidn_timing=False, track=False)
    storage.remove_tree(dataset)
    record = run(store, storage, settings, job_id)
    assert record["state"] == "failed" and record["result"] is None
    assert record["error"] == {"code": "dataset_not_found", "message": "dataset 'tiny' does not exist"}
    assert "failed: dataset 'tiny' does not exist" in (storage.job(job_id) / "job.log").read_text()


def test_a_duplicate_delivery_returns_at_once(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "evaluate", dataset="tiny", methods=["identity"], vdp=False,
                    oidn_timing=False, track=False)
    store.redis.set(store.lease_key(job_id), "another-worker")
    assert execute(job_id, store, storage, settings)["skipped"] == "busy"
    store.redis.delete(store.lease_key(job_id))
    assert run(store, storage, settings, job_id)["state"] == "succeeded"
    summary = execute(job_id, store, storage, settings)
    assert summary == {"job_id": job_id, "state": "succeeded", "skipped": "finished"}
    assert store.get(job_id)["attempts"] == 1
    assert execute("unknown", store, storage, settings)["skipped"] == "missing"


# --------------------------------------------------------------------------------------------- train

def test_train_tracks_registers_and_links_the_mlflow_run(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "train",
                    **train_params(track=True, register_as="tiny-jobs", validate_every=3))
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    result = record["result"]
    assert result["steps"] == 3 and result["checkpoint"] == f"jobs/{job_id}/checkpoints/last.pt"
    assert result["registered_model"]["uri"] == "models:/tiny-jobs/1"
    assert record["mlflow_run_id"] == result["run_id"]
    assert record["mlflow_url"].startswith("http://mlflow.test:5000/#/experiments/")
    assert record["mlflow_url"].endswith(f"/runs/{result['run_id']}")


def _shipped_tiny(tmp_path, monkeypatch, name="tiny-x1"):
    """A seeded tiny_test checkpoint shipped as a pretrained model in a tmp pretrained folder."""
    import model.deployment.pretrained as pretrained
    from model.training.checkpoint import save_checkpoint

    monkeypatch.setattr(pretrained, "PRETRAINED_DIR", tmp_path / "pretrained")
    torch.manual_seed(11)
    source = save_checkpoint(tmp_path / "tiny.pt", method=build_method(TINY_METHOD, 1), step=5,
                             train_config={"steps": 5, "seed": 11})
    return pretrained.ship_checkpoint(source, name)


def test_a_training_starts_from_a_pretrained_model_or_a_registered_one(store, storage, settings, dataset, tmp_path,
                                                                       monkeypatch):
    from model.training.checkpoint import load_checkpoint

    shipped = _shipped_tiny(tmp_path, monkeypatch)
    initial = load_checkpoint(shipped.path)["model"]
    # A learning rate this small leaves the weights where they started: the start is what init_from gave.
    job_id = submit(store, storage, settings, "train",
                    **train_params(steps=1, lr=1e-12, init_from="tiny-x1", track=True, register_as="tiny-tuned"))
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    tuned = load_checkpoint(storage.root / record["result"]["checkpoint"])["model"]
    assert tuned.keys() == initial.keys()
    for key in initial:
        torch.testing.assert_close(tuned[key], initial[key], atol=1e-9, rtol=0)
    scratch = run(store, storage, settings, submit(store, storage, settings, "train", **train_params(steps=1)))
    from_scratch = load_checkpoint(storage.root / scratch["result"]["checkpoint"])["model"]
    assert any(not torch.allclose(from_scratch[key], initial[key]) for key in initial)
    # The registered result is a models:/ reference a next fine-tune can start from (references resolve through
    # the configured settings, as in the API).
    from core.settings import get_settings

    monkeypatch.setenv("DENOISER_TRACKING_URI", settings.tracking_uri)
    monkeypatch.setenv("DENOISER_DATA_DIR", str(settings.data_dir))
    get_settings.cache_clear()
    again = submit(store, storage, settings, "train", **train_params(steps=1, init_from="models:/tiny-tuned/1"))
    try:
        assert run(store, storage, settings, again)["state"] == "succeeded"
    finally:
        get_settings.cache_clear()


def test_int8_jnds_trains_from_a_float_checkpoint_with_every_training_option(store, storage, settings, dataset):
    """Quantization-aware training of jnds:xs-int8 from a float32 jnds:xs job's checkpoint, through the job code
    with the options only the CLI used to have (epochs, loss weights, tone map, skipped frames, schedule)."""
    from model.training.checkpoint import load_checkpoint

    float_job = run(store, storage, settings, submit(store, storage, settings, "train",
                                                     **train_params(method="jnds:xs", crop=16, steps=1)))
    assert float_job["state"] == "succeeded", float_job["error"]
    float_checkpoint = float_job["result"]["checkpoint"]
    options = dict(method="jnds:xs-int8", init_from=float_checkpoint, crop=16, epochs=1, lr=1e-12,
                   schedule="constant", spatial_weight=1.0, temporal_weight=0.5, tonemap="mulaw",
                   loss_skip_frames=1, grad_clip=0.5, augment=False, min_lr_ratio=0.1)
    params = train_params(**options)
    del params["steps"]  # epochs instead
    job_id = submit(store, storage, settings, "train", **params)
    stored = store.get(job_id)["params"]
    assert stored["steps"] is None and {key: stored[key] for key in options} == options
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    tuned = load_checkpoint(storage.root / record["result"]["checkpoint"])
    assert tuned["method"]["preset"] == "xs-int8"
    assert tuned["train_config"]["tonemap"] == "mulaw" and tuned["train_config"]["loss_skip_frames"] == 1
    assert tuned["step"] == record["result"]["steps"] >= 1  # one epoch of the 2 training sequences' windows
    start = load_checkpoint(storage.root / float_checkpoint)["model"]
    for key, value in start.items():  # a tiny learning rate: the int8 model starts from the float weights
        torch.testing.assert_close(tuned["model"][key], value, atol=1e-6, rtol=0)


@pytest.mark.parametrize("shipped", [True, False])
def test_a_fused_training_job_from_nothing_takes_the_shipped_settings_unless_told_not_to(store, storage, settings,
                                                                                         dataset, shipped):
    from model.training.checkpoint import load_method
    from model.methods.fused import SHIPPED_SETTINGS

    record = run(store, storage, settings, submit(store, storage, settings, "train", **train_params(
        method="fused:fast", crop=16, steps=1, shipped_settings=shipped)))
    assert record["state"] == "succeeded", record["error"]
    trained = load_method(storage.root / record["result"]["checkpoint"])
    expected = SHIPPED_SETTINGS[1] if shipped else {"sample_mean_frames": 0, "stale_test_sigmas": 0.0,
                                                     "stale_region_pixels": 0, "history_before_kernel": False}
    assert {name: getattr(trained, name) for name in expected} == expected


@pytest.mark.parametrize("init_from, error_type, code, words", [
    ("nothing-here", NotFound, "init_from_not_found", "pretrained models: tiny-x1"),
    ("identity", NotFound, "init_from_not_found", "a method name has no weights"),
    ("models:/no-such-model@pretrained", NotFound, "model_not_found", "does not exist"),
    ("wskpn-xs-x1", Invalid, "invalid_init_from", "holds wskpn:xs at scale 1; it cannot start tiny_test"),
])
def test_a_bad_init_from_is_refused_before_queueing(store, storage, settings, dataset, tmp_path, monkeypatch,
                                                    init_from, error_type, code, words):

    _shipped_tiny(tmp_path, monkeypatch)
    if init_from == "wskpn-xs-x1":  # another family
        import model.deployment.pretrained as pretrained
        from model.training.checkpoint import save_checkpoint

        pretrained.ship_checkpoint(save_checkpoint(tmp_path / "w.pt", method=build_method("wskpn:xs", 1)), init_from)
    with pytest.raises(DomainError) as caught:
        submit(store, storage, settings, "train", **train_params(init_from=init_from))
    assert (type(caught.value), caught.value.code) == (error_type, code)
    assert words in str(caught.value)


def test_a_cancelled_training_resumes_from_its_checkpoint_when_run_again(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "train", **train_params(steps=100_000, checkpoint_every=1))

    def cancel_once_started(report: dict) -> None:
        if report["current"] >= 1 and not store.cancel_requested(job_id):
            store.request_cancel(job_id)

    record = run(store, storage, settings, job_id, reports=_Calls(cancel_once_started))
    assert record["state"] == "cancelled" and record["progress"]["current"] >= 1
    from model.training.checkpoint import load_checkpoint

    stopped_at = load_checkpoint(storage.job(job_id) / "checkpoints" / "last.pt")["step"]
    assert stopped_at >= 1
    # The same job delivered again (as recovery does after a lost worker), with a reachable end.
    store.update(job_id, state="queued", finished_at=None, cancel_requested=False,
                 params={**record["params"], "steps": stopped_at + 2})
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    assert record["attempts"] == 2 and record["result"]["steps"] == stopped_at + 2
    assert "resuming from" in (storage.job(job_id) / "job.log").read_text()


class _Calls(list):
    """A progress sink that also calls a function with every report."""

    def __init__(self, function) -> None:
        super().__init__()
        self.function = function

    def append(self, report: dict) -> None:
        super().append(report)
        self.function(report)


class FakeRanks:
    """Stands in for workers.ddp.TrainingJob: 'trains' until stopped, as real ranks would."""

    instances: list = []

    def __init__(self, config, *, track: bool, imports) -> None:
        self.config, self.track, self.imports = config, track, imports
        self.stopped = threading.Event()
        self.process = type("Process", (), {"pid": 4242})()
        self.port = 29500
        self.log_path = "ddp.log"
        FakeRanks.instances.append(self)

    def start(self) -> None:
        pass

    def wait(self, progress) -> dict:
        progress(1, self.config.steps, "step 1")
        while not self.stopped.wait(0.05):
            pass
        from workers.ddp import RankError

        raise RankError("training job failed (launcher exit status -15)")

    def stop(self, grace: float = 10.0) -> None:
        self.stopped.set()

    def log_tail(self, lines: int = 30) -> str:
        return "(fake)"


def test_cancel_stops_ddp_ranks_through_training_job_stop(store, storage, settings, dataset, monkeypatch):
    monkeypatch.setattr("workers.ddp.TrainingJob", FakeRanks)
    job_id = submit(store, storage, settings, "train", **train_params(world_size=2, steps=1000))

    def cancel_once_running(report: dict) -> None:
        # Cancelled once the ranks report a step, not after a fixed delay: a cancel that landed before the job
        # started would end it without ever reaching the ranks.
        if report["current"] >= 1 and not store.cancel_requested(job_id):
            store.request_cancel(job_id)

    started = time.monotonic()
    record = run(store, storage, settings, job_id, reports=_Calls(cancel_once_running))
    assert record["state"] == "cancelled", record["error"]
    ranks = FakeRanks.instances[-1]
    assert ranks.stopped.is_set() and ranks.config.world_size == 2 and ranks.config.resume
    assert ranks.config.out == str(storage.job(job_id) / "checkpoints")
    assert "tests.model.training_fixtures" in ranks.imports  # the test method's module, for the ranks
    assert time.monotonic() - started < 5


def test_plugin_modules_are_the_registering_modules_outside_the_registry():
    assert "tests.model.training_fixtures" in plugin_modules()
    assert not any(m.startswith("model.methods") for m in plugin_modules())


@pytest.mark.slow
def test_cancel_ends_real_ddp_ranks(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "train", **train_params(world_size=2, steps=100_000))
    record = run(store, storage, settings, job_id,
                 reports=_Calls(lambda report: store.request_cancel(job_id) if not store.cancel_requested(job_id)
                                else None))
    assert record["state"] == "cancelled", record["error"]


# --------------------------------------------------------------------------------------------- infer

def test_infer_writes_one_exr_per_frame_with_history_carried(store, storage, settings, dataset):
    job_id = submit(store, storage, settings, "infer", dataset="tiny", model="accumulation", split="test")
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    assert record["result"]["frames"] == 8 and record["result"]["method"]["label"] == "accumulation"
    files = sorted(p.relative_to(storage.result(job_id)).as_posix() for p in storage.result(job_id).rglob("*.exr"))
    assert files == [f"{s}/frame_{i:04d}.exr" for s in ("delta", "epsilon") for i in range(4)]
    # The outputs are exactly what stepping the method through the sequence with its state gives.
    method = build_method("accumulation").eval()
    sequence = Dataset(dataset).sequence("epsilon")
    state = None
    for index in range(len(sequence)):
        with torch.inference_mode():
            expected, state = method.step(FrameBatch.from_bundles([sequence[index]], scale=None), state)
        exr = OpenEXR.File(str(storage.result(job_id) / "epsilon" / f"frame_{index:04d}.exr"),
                           separate_channels=True)
        channels = exr.parts[0].channels
        written = np.stack([channels[c].pixels for c in "RGB"], axis=-1)
        assert exr.parts[0].header["frame_index"] == index
        np.testing.assert_array_equal(written, expected[0].permute(1, 2, 0).numpy())


# ------------------------------------------------------------------------------------------- generate

def fake_generate_sequence(scene, out, *, frames, settings, seed, split, name, half, overwrite, progress,
                           on_frame):
    """Writes synthetic frames where Mitsuba would render (the job's plumbing is what is tested here)."""
    from model.io.dataset import Dataset

    dataset = Dataset.open_or_create(out)
    write_sequence(out, name, frames, size=(settings.width, settings.height), seed=seed)
    for index in range(frames):
        on_frame(index + 1, frames, f"rendered frame {index + 1}/{frames} of {name}")
    dataset.add_sequence_dir(name, split, replace=overwrite)
    return out / name


def test_generate_creates_the_dataset_and_adds_whole_sequences(store, storage, settings, monkeypatch):
    monkeypatch.setattr("model.data.generate.generate_sequence", fake_generate_sequence)
    job_id = submit(store, storage, settings, "generate", dataset="fresh", scenes=["metals", "diffuse_room"],
                    frames=2, size=8, ref_spp=4, split="validation")
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    assert record["result"]["sequences"] == ["metals_s0", "diffuse_room_s0"]
    dataset = Dataset(storage.dataset("fresh"))
    assert dataset.names("validation") == ["diffuse_room_s0", "metals_s0"]
    assert record["progress"]["current"] == record["progress"]["total"] == 4
    assert not (storage.job(job_id) / "render").exists()


def test_generate_passes_jitter_to_the_renderer(store, storage, settings, monkeypatch):
    given = []

    def recording(scene, out, **kwargs):
        given.append(kwargs["settings"].jitter)
        return fake_generate_sequence(scene, out, **kwargs)

    monkeypatch.setattr("model.data.generate.generate_sequence", recording)
    for dataset, jitter in (("centred", {"jitter": False}), ("jittered", {})):
        job_id = submit(store, storage, settings, "generate", dataset=dataset, scenes=["metals"], frames=1, size=8,
                        **jitter)
        assert run(store, storage, settings, job_id)["state"] == "succeeded"
    assert given == [False, True]


def test_generate_resumed_renders_only_what_was_not_published(store, storage, settings, monkeypatch):
    rendered = []

    def counting(scene, out, **kwargs):
        rendered.append(scene)
        return fake_generate_sequence(scene, out, **kwargs)

    monkeypatch.setattr("model.data.generate.generate_sequence", counting)
    job_id = submit(store, storage, settings, "generate", dataset="resumed", scenes=["metals", "diffuse_room"],
                    frames=2, size=8)
    # A lost execution had published the first sequence (and half-rendered the second).
    (storage.job(job_id)).mkdir(parents=True)
    generate_module.publish(storage, "resumed", fake_generate_sequence(
        "diffuse_room", storage.job(job_id) / "render" / "x", frames=2, settings=_Size(8), seed=0, split="train",
        name="diffuse_room_s0", half=False, overwrite=False, progress=False, on_frame=lambda *a: None),
        "train", replace=False)
    (storage.job(job_id) / generate_module.PUBLISHED_FILE).write_text(json.dumps(["diffuse_room_s0"]))
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    assert rendered == ["metals"] and record["result"]["sequences"] == ["diffuse_room_s0", "metals_s0"]


def test_generate_renders_a_tiny_sequence_with_mitsuba(store, storage, settings):
    pytest.importorskip("mitsuba")
    job_id = submit(store, storage, settings, "generate", dataset="rendered", scenes=["diffuse_room"], frames=2,
                    size=8, ref_spp=4, albedo_spp=1, scales=[1])
    record = run(store, storage, settings, job_id)
    assert record["state"] == "succeeded", record["error"]
    sequence = Dataset(storage.dataset("rendered")).sequence("diffuse_room_s0")
    assert len(sequence) == 2 and (sequence.width, sequence.height) == (8, 8) and sequence.scales == (1,)


class _Size:
    def __init__(self, size: int) -> None:
        self.width = self.height = size


# --------------------------------------------------------------------------------------------- lease

def test_the_watchdog_notices_a_lost_lease_and_a_cancel(store, storage, settings):
    job_id = store.create("evaluate", {}, "cpu", "cpu")["id"]
    store.start(job_id, "me")
    context = JobContext(store.get(job_id), store, storage, settings, "me")
    stopped = []
    context.on_cancel(lambda: stopped.append(True))
    with Watchdog(context, heartbeat_interval=0.05, watch_interval=0.02):
        store.request_cancel(job_id)
        assert context.cancelled.wait(2)
        store.redis.set(store.lease_key(job_id), "someone-else")
        assert context.lease_lost.wait(2)
    assert stopped


# ----------------------------------------------------------------------------------- test-only parking

def test_the_parking_hook_changes_nothing_unless_a_test_asks_and_parks_the_first_attempt_only(
        store, storage, settings, tmp_path):
    from tests.workers.parking import parked_progress

    parking = tmp_path / "parking"
    parking.mkdir()
    job_id = store.create("train", {"register_as": "parked-model"}, "cpu", "cpu")["id"]
    store.start(job_id, "me")
    context = JobContext(store.get(job_id), store, storage, settings, "me")
    calls = []

    def progress(current, total, message=""):
        calls.append(current)

    assert parked_progress(context, progress, None) is progress  # no folder: the callback itself
    assert parked_progress(context, progress, parking) is progress  # no request for this model
    (parking / "parked-model.park").write_text("2")
    retried = JobContext({**store.get(job_id), "attempts": 2}, store, storage, settings, "me")
    assert parked_progress(retried, progress, parking) is progress  # a later attempt runs on

    parked = parked_progress(context, progress, parking)
    parked(1, 4)
    assert calls == [1] and not (parking / "parked-model.parked").exists()
    context.cancelled.set()  # parked, the job still ends on a cancel, as in any step
    with pytest.raises(JobCancelled):
        parked(2, 4)
    assert calls == [1, 2] and (parking / "parked-model.parked").read_text() == "2"
    assert sorted(p.name for p in parking.iterdir()) == ["parked-model.park", "parked-model.parked"]
