"""The ``stability`` job: model.evaluation.stability's suite on a stored dataset (its scenes and corrupted copies).

Writes what ``denoiser stability`` writes (``model.evaluation.stability_report.write_report``) into the job folder:
``stability.json``, ``stability.md`` and the charts; the result names each method's worst scenario and the
temporal method that ghosts least. With ``track`` the run goes to MLflow (experiment ``denoiser-stability``):
parameters, each method's median gain, failures and mean ghost error, and the files as artifacts.
"""

from __future__ import annotations

from typing import Any

from core.jobs.files import STABILITY_FILES
from core.jobs.methods import runnable
from core.jobs.specs import StabilityParams
from core.jobs.stability import scenario_names
from workers.tasks.context import JobContext
from workers.tasks.evaluate import metric_key

EXPERIMENT = "denoiser-stability"


def run(context: JobContext) -> dict[str, Any]:
    from model.evaluation.stability import build_scenarios, run_suite
    from model.evaluation.stability_report import write_report

    params = StabilityParams.model_validate(context.params)
    scenarios, missing = build_scenarios(context.storage.dataset(params.dataset), params.scale,
                                         names=scenario_names(params), base=params.base, frame_limit=params.frames,
                                         seed=params.seed)
    for entry in missing:
        context.logger.info("skipping scenario %s: %s", entry["name"], entry["reason"])
    if not scenarios:
        raise ValueError(f"none of the scenarios can be built from dataset {params.dataset!r}")
    total = len(params.methods) * len(scenarios)
    runs = 0

    def say(message: str) -> None:
        nonlocal runs
        if " FAILED: " in message:  # a second line about the run just reported
            context.logger.warning(message)
            return
        context.progress(runs, total, message)
        runs += 1

    tracker = _start_tracking(context, params) if params.track else None
    with context.ending(tracker):
        report = run_suite(scenarios, [runnable(m, context.storage) for m in params.methods], params.scale,
                           vdp=params.vdp, device=context.torch_device, threads=params.threads, progress=say,
                           missing=missing, data=params.dataset)
        for entry, text in zip(report["methods"], params.methods):
            entry["source"] = text  # the reference as given, not the cached checkpoint's path
        context.progress(total, total, "writing the report")
        files = write_report(report, context.folder)
        if tracker is not None:
            _log_results(tracker, report, files)
    written = {path.name for path in files.values()}
    return {
        "dataset": params.dataset, "scale": params.scale, "device": report["device"], "threads": report["threads"],
        "scenarios": [s["name"] for s in report["scenarios"]], "missing_scenarios": report["missing_scenarios"],
        "methods": [{"label": e["label"], "source": e["source"], "temporal": e["temporal"],
                     "median_gain_db": e["median_gain_db"], "worst": e["worst"], "failures": e["failures"]}
                    for e in report["methods"]],
        "ghosting": {key: report["ghosting"][key] for key in ("least", "mean_error", "common_scenarios")},
        "artifacts": {name: f"/jobs/{context.job_id}/artifacts/{name}" for name in STABILITY_FILES
                      if name in written},
    }


def _start_tracking(context: JobContext, params: StabilityParams):
    from core.tracking import MLflowTracker

    tracker = MLflowTracker(context.settings.resolved_tracking_uri(), EXPERIMENT,
                            run_name=f"stability {params.dataset} (job {context.job_id[:8]})")
    tracker.start({"kind": "stability", "job_id": context.job_id, "dataset": params.dataset, "scale": params.scale,
                   "methods": ",".join(params.methods), "scenarios": ",".join(scenario_names(params)),
                   "frames": params.frames, "seed": params.seed, "vdp": params.vdp, "device": context.torch_device})
    context.set_mlflow_run(tracker.run_id, getattr(tracker, "_experiment_id", None))
    tracker.log_dataset(context.storage.dataset(params.dataset), "stability")
    return tracker


def _log_results(tracker, report: dict, files: dict) -> None:
    metrics: dict[str, float] = {}
    ghost = report["ghosting"]["mean_error"]
    for entry in report["methods"]:
        name = metric_key(entry["source"])
        values = {"median_gain_db": entry["median_gain_db"], "failures": float(len(entry["failures"])),
                  "mean_ghost_error": ghost.get(entry["label"])}
        metrics.update({f"{name}/{key}": value for key, value in values.items() if value is not None})
    tracker.log_metrics(metrics, step=0)
    for path in files.values():
        if path.name in STABILITY_FILES:
            tracker.client.log_artifact(tracker.run_id, str(path))
