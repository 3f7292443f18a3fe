"""The ``train`` job: model.train in this process, or in ``world_size`` DDP ranks (workers.ddp), tracked in MLflow.

Checkpoints go to ``jobs/<id>/checkpoints`` with ``resume=True``, so an execution that follows a lost worker
continues from the last checkpoint (and the same MLflow run, whose id the checkpoint carries). When the lost
execution had already written its final checkpoint, the model is registered from it (unless the run already has
a registered version) instead of training again.

Cancellation: one process stops at the next step through the progress callback (``JobCancelled``); DDP ranks
are stopped as a whole by ``TrainingJob.stop`` (their process group), called from the job's watchdog thread as
soon as the cancel flag is seen.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

from model.dataset import Dataset
from service.errors import ApiError
from service.schemas import TrainParams
from service.settings import Settings
from service.storage import Storage
from workers.tasks.checks import invalid, open_dataset, split_sequences
from workers.tasks.context import JobContext
from workers.tasks.methods import check_registry_method, checkpoint_method, checkpoint_source

CHECKPOINT_FOLDER = "checkpoints"


def train_config(params: TrainParams, storage: Storage, settings: Settings, out: Path, device: str,
                 init_from: Path | None = None):
    """``init_from``: the local checkpoint ``params.init_from`` stands for (``initial_weights``)."""
    from model.train import TrainConfig

    return TrainConfig(
        method=params.method, data=str(storage.dataset(params.dataset)), scale=params.scale,
        train_split=params.train_split, validation_split=params.validation_split, crop_size=params.crop,
        frames_per_sample=params.frames_per_sample, batch_size=params.batch, steps=params.steps, lr=params.lr,
        schedule=params.schedule, warmup_steps=params.warmup_steps, seed=params.seed, out=str(out), resume=True,
        device=device, world_size=params.world_size, checkpoint_every=params.checkpoint_every,
        validate_every=params.validate_every, validation_frames=params.validation_frames,
        num_threads=params.threads or rank_threads(settings, params.world_size),
        tracking_uri=settings.resolved_tracking_uri(), experiment=params.experiment,
        register_as=params.register_as, init_from=str(init_from) if init_from else None)


def initial_weights(params: TrainParams, storage: Storage) -> Path | None:
    """The checkpoint ``init_from`` names (a registered model, a pretrained model or a stored checkpoint), checked
    to hold the job's method family at its scale; ApiError 404 / 422 otherwise."""
    if params.init_from is None:
        return None
    path = checkpoint_source(params.init_from, storage)
    if path is None:
        from model.pretrained import pretrained_names

        raise ApiError(404, "init_from_not_found", f"init_from {params.init_from!r} is no registered model "
                       f"(models:/NAME@ALIAS), pretrained model or checkpoint (a method name has no weights); "
                       f"pretrained models: {', '.join(pretrained_names()) or 'none'}")
    source = checkpoint_method(path, f"init_from {params.init_from!r}")
    family = params.method.partition(":")[0]
    if source.get("method") != family or source.get("scale") != params.scale:
        raise ApiError(422, "invalid_init_from", f"init_from {params.init_from!r} holds {source.get('method')}:"
                       f"{source.get('preset')} at scale {source.get('scale')}; it cannot start {params.method} at "
                       f"scale {params.scale}")
    return path


def rank_threads(settings: Settings, world_size: int) -> int | None:
    """Each rank's share of DENOISER_JOB_THREADS (None: unset, each rank takes its share of the cores)."""
    if not settings.job_threads:
        return None
    return max(1, settings.job_threads // max(1, world_size))


def check(params: TrainParams, storage: Storage, settings: Settings) -> dict[str, Any]:
    """Everything ``model.train.prepare`` would refuse, found from manifests alone (no frame is decoded)."""
    from model.data.crops import sample_windows

    dataset = open_dataset(storage, params.dataset)
    check_registry_method(params.method, params.scale, learned=True)
    init_from = initial_weights(params, storage)
    try:
        train_config(params, storage, settings, storage.jobs / "_check", "cpu", init_from).check()
    except ValueError as error:
        raise invalid(error) from None
    sequences = split_sequences(dataset, params.dataset, params.train_split, params.scale)
    small = [s for s in sequences if s.width < params.crop or s.height < params.crop]
    if small:
        raise ApiError(422, "crop_too_large", f"sequence '{small[0].name}' is {small[0].width}x{small[0].height}, "
                       f"smaller than the {params.crop}x{params.crop} crop; use a smaller crop")
    if not any(sample_windows(s.cuts, len(s), params.frames_per_sample) for s in sequences):
        raise ApiError(422, "sequences_too_short", f"no sequence of split {params.train_split!r} has "
                       f"{params.frames_per_sample} consecutive frames without a camera cut; use fewer "
                       f"frames_per_sample")
    _check_validation_split(dataset, params)
    return params.model_dump()


def _check_validation_split(dataset: Dataset, params: TrainParams) -> None:
    missing = [s.name for s in dataset.sequences(params.validation_split) if params.scale not in s.scales]
    if missing:
        raise ApiError(422, "missing_scale", f"validation sequence(s) {', '.join(missing[:5])} have no references "
                       f"at scale {params.scale}")


def run(context: JobContext) -> dict[str, Any]:
    from model.checkpoint import load_checkpoint
    from model.train import LAST_CHECKPOINT

    params = TrainParams.model_validate(context.params)
    out = context.folder / CHECKPOINT_FOLDER
    config = train_config(params, context.storage, context.settings, out, context.torch_device,
                          initial_weights(params, context.storage))
    last = out / LAST_CHECKPOINT
    if last.is_file():
        checkpoint = load_checkpoint(last)
        context.baseline = int(checkpoint["step"])
        context.set_mlflow_run(checkpoint["extra"].get("tracking_run_id"))
        context.logger.info("resuming from %s at step %d of %d", last, checkpoint["step"], params.steps)
        if checkpoint["step"] >= params.steps:
            return _relative(context, _completed(context, params, checkpoint, last))
    if params.world_size == 1:
        result = _train_here(context, config, params.track, params)
    else:
        result = _train_ranks(context, config, params.track)
    return _relative(context, result)


class _JobTracker:
    """MLflowTracker that puts the run id into the job record as soon as the run exists, and ends a cancelled
    job's run as KILLED rather than FAILED."""

    def __init__(self, inner, context: JobContext) -> None:
        self.inner = inner
        self.context = context

    @property
    def run_id(self) -> str | None:
        return self.inner.run_id

    def start(self, params: dict[str, Any], resume_run_id: str | None = None) -> None:
        self.inner.start(params, resume_run_id)
        self.context.set_mlflow_run(self.inner.run_id, getattr(self.inner, "_experiment_id", None))

    def log_metrics(self, metrics: dict[str, float], step: int) -> None:
        self.inner.log_metrics(metrics, step)

    def log_image_grid(self, name: str, columns, step: int) -> None:
        self.inner.log_image_grid(name, columns, step)

    def log_dataset(self, path: str, context: str) -> None:
        self.inner.log_dataset(path, context)

    def log_model(self, checkpoint: Path, registered_name: str, tags: dict[str, str]):
        return self.inner.log_model(checkpoint, registered_name, tags)

    def finish(self, status: str) -> None:
        self.inner.finish("KILLED" if self.context.cancelled.is_set() and status == "FAILED" else status)


def _tracker(context: JobContext, config, track: bool):
    if not track:
        return None
    from workers.tracking import MLflowTracker

    return _JobTracker(MLflowTracker(config.tracking_uri, config.experiment,
                                     run_name=f"{config.method} (job {context.job_id[:8]})"), context)


# Test-only: a folder in which a test asks a training job to park (see ``_parked_progress``). Unset in every
# deployment; the end-to-end tests set it to kill a worker while its job is at a known step, not by racing it.
TEST_PARKING_ENV = "DENOISER_TEST_PARKING_DIR"


def _parked_progress(context: JobContext, params: TrainParams, progress):
    """Test-only hook: with ``$DENOISER_TEST_PARKING_DIR`` set and a file ``<register_as>.park`` in it holding a step,
    the job's first attempt writes ``<register_as>.parked`` once that step is reported (its checkpoint is already
    written then) and waits there until its worker is killed (or, as in any step, a cancel or a lost lease ends
    it). Later attempts and other jobs run as usual; unset, the progress callback is returned unchanged."""
    folder = os.environ.get(TEST_PARKING_ENV)
    if not folder or not params.register_as or int(context.record.get("attempts") or 1) != 1:
        return progress
    request = Path(folder) / f"{params.register_as}.park"
    if not request.is_file():
        return progress
    park_at = int(request.read_text().strip())

    def parked(current: int, total: int, message: str = "") -> None:
        progress(current, total, message)
        if current == park_at:
            # Written whole, then renamed: the test reads the step as soon as the file exists.
            marker = Path(folder) / f"{params.register_as}.parked"
            partial = marker.with_suffix(".partial")
            partial.write_text(str(current))
            partial.replace(marker)
            while True:
                context.check()
                time.sleep(0.05)

    return parked


def _train_here(context: JobContext, config, track: bool, params: TrainParams) -> dict[str, Any]:
    from model.train import train

    return train(config, tracker=_tracker(context, config, track),
                 progress=_parked_progress(context, params, context.progress))


def plugin_modules() -> list[str]:
    """Modules that registered methods from outside the registry's own list (imported into this worker, e.g. with
    ``celery worker -I``): the ranks must import them too to find those methods."""
    from model.methods.registry import METHOD_MODULES, REGISTRY

    modules = {getattr(spec.factory, "__module__", None) for spec in REGISTRY.values()}
    return sorted(m for m in modules if m and m not in METHOD_MODULES and m != "__main__")


def _train_ranks(context: JobContext, config, track: bool) -> dict[str, Any]:
    from workers.ddp import RankError, TrainingJob

    job = TrainingJob(config, track=track, imports=plugin_modules())
    stop_lock = threading.Lock()

    def stop() -> None:
        with stop_lock:  # the watchdog (cancel) and this thread (the end) may both stop the job
            job.stop()

    job.start()
    context.logger.info("started %d DDP ranks (launcher pid %d, rendezvous port %d)", config.world_size,
                        job.process.pid, job.port)
    unregister = context.on_cancel(stop)
    try:
        result = job.wait(context.progress)
    except RankError:
        context.check()  # ranks stopped because of a cancel (or a lost lease): say that, not "ranks failed"
        raise
    finally:
        unregister()
        stop()
        context.logger.info("end of the ranks' log (%s):\n%s", job.log_path, job.log_tail(40))
    context.set_mlflow_run(result.get("run_id"))
    return result


def _completed(context: JobContext, params: TrainParams, checkpoint: dict, last: Path) -> dict[str, Any]:
    """The result of a training whose final checkpoint exists (its execution was lost before the end)."""
    registered = None
    run_id = checkpoint["extra"].get("tracking_run_id")
    if params.track:
        registered = _register_once(context, params, checkpoint, last, run_id)
    best = last.with_name("best.pt")
    return {"rank": 0, "steps": checkpoint["step"], "epochs": checkpoint.get("epoch"), "losses": {},
            "validation": None, "best_metric": checkpoint.get("best_metric"), "checkpoint": str(last),
            "best_checkpoint": str(best) if best.is_file() else None, "run_id": run_id,
            "registered_model": registered, "resumed_complete": True}


def _register_once(context: JobContext, params: TrainParams, checkpoint: dict, last: Path,
                   run_id: str | None) -> dict[str, Any] | None:
    from model.checkpoint import load_method
    from model.methods.registry import inference_cost
    from model.train import default_registered_name
    from workers.tracking import MLflowTracker

    tracker = MLflowTracker(context.settings.resolved_tracking_uri(), params.experiment)
    if run_id:
        versions = tracker.client.search_model_versions(f"run_id = '{run_id}'")
        if versions:
            version = max(versions, key=lambda v: int(v.version))
            return {"name": version.name, "version": str(version.version), "model_id": None,
                    "uri": f"models:/{version.name}/{version.version}"}
    method = load_method(last)
    tracker.start({"method": params.method}, resume_run_id=run_id)
    context.set_mlflow_run(tracker.run_id)
    params_count, flops = inference_cost(method)
    tags = {"method": method.name, "preset": method.preset, "scale": str(method.scale),
            "params": str(params_count), "flops_per_pixel": f"{flops:.6g}",
            "steps": str(checkpoint["step"])}
    registered = tracker.log_model(last, params.register_as or default_registered_name(method), tags)
    tracker.finish("FINISHED")
    return registered


def _relative(context: JobContext, result: dict[str, Any]) -> dict[str, Any]:
    """Checkpoint paths relative to the data folder: what evaluate and infer jobs accept as a method."""
    root = context.storage.root.resolve()
    for key in ("checkpoint", "best_checkpoint"):
        value = result.get(key)
        if value:
            path = Path(value).resolve()
            result[key] = str(path.relative_to(root)) if path.is_relative_to(root) else value
    return result
