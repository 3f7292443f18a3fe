"""The ``train`` job: model.training.train in this process, or in ``world_size`` DDP ranks (workers.ddp), or on
``nodes`` workers (workers.tasks.nodes), tracked in MLflow.

Checkpoints go to ``jobs/<id>/checkpoints`` with ``resume=True``, so an execution that follows a lost worker
continues from the last checkpoint (and the same MLflow run, whose id the checkpoint carries). When the lost
execution had already written its final checkpoint, the model is registered from it (unless the run already has
a registered version) instead of training again.

Cancellation: one process stops at the next step through the progress callback (``JobCancelled``); DDP ranks
are stopped as a whole by ``TrainingJob.stop`` (their process group), called from the job's watchdog thread as
soon as the cancel flag is seen.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from core.jobs.files import CHECKPOINT_FOLDER
from core.jobs.specs import TrainParams
from core.jobs.train import initial_weights, train_config
from workers.tasks.context import JobContext


def run(context: JobContext) -> dict[str, Any]:
    from model.training.checkpoint import load_checkpoint
    from model.training.train import LAST_CHECKPOINT

    params = TrainParams.model_validate(context.params)
    out = context.folder / CHECKPOINT_FOLDER
    config = train_config(params, context.storage, context.settings, out, context.torch_device,
                          initial_weights(params, context.storage))
    last = out / LAST_CHECKPOINT
    if last.is_file():
        checkpoint = load_checkpoint(last)
        context.baseline = int(checkpoint["step"])
        context.set_mlflow_run(checkpoint["extra"].get("tracking_run_id"))
        # Under epochs the number of steps is known once the data is read: the checkpoint carries it.
        total = checkpoint["extra"].get("total_steps") or params.steps
        context.logger.info("resuming from %s at step %d of %s", last, checkpoint["step"], total)
        if total is not None and checkpoint["step"] >= total:
            return _relative(context, _completed(context, params, checkpoint, last))
    if params.nodes > 1:
        from workers.tasks.nodes import train_on_nodes

        result = train_on_nodes(context, config, params)
    elif params.world_size == 1:
        result = _train_here(context, config, params.track)
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


def job_tracker(context: JobContext, config, track: bool):
    if not track:
        return None
    from core.tracking import MLflowTracker

    return _JobTracker(MLflowTracker(config.tracking_uri, config.experiment,
                                     run_name=f"{config.method} (job {context.job_id[:8]})"), context)


def _train_here(context: JobContext, config, track: bool) -> dict[str, Any]:
    from model.training.train import train

    return train(config, tracker=job_tracker(context, config, track), progress=context.progress)


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
    from model.training.checkpoint import load_method
    from model.methods.registry import inference_cost
    from model.training.train import default_registered_name
    from core.tracking import MLflowTracker

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
