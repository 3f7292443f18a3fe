"""The ``fit`` job (right-sizing, ``model.fit``); its MLflow side, shared with the CLI, is ``core.fit_tracking``.

The job trains into ``jobs/<id>/fit/<preset>-<key>/`` (an execution that follows a lost worker resumes there),
writes ``ladder.json`` and ``ladder.md`` into the job folder, and ends ``succeeded`` with the ladder in its result,
or ``failed`` with code ``target_not_met`` when no preset meets the target (the ladder files are written anyway).
Cancellation: the progress callback of every training step and measurement raises ``JobCancelled``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from core.fit_tracking import start_fit_run
from core.jobs.fit import fit_config
from core.jobs.specs import FitParams
from workers.tasks.context import JobContext, JobFailure

FIT_FOLDER = "fit"


# -------------------------------------------------------------------------------------------------- the job


def run(context: JobContext) -> dict[str, Any]:
    from model.fit.plan import plan_fit
    from model.fit.report import LADDER_JSON, LADDER_MARKDOWN, format_ladder, write_ladder
    from model.fit.runner import fit

    params = FitParams.model_validate(context.params)
    config = fit_config(params, context.storage, context.settings, context.folder / FIT_FOLDER,
                        context.torch_device)
    plan = plan_fit(config)
    recorder = None
    if params.track:
        recorder = start_fit_run(config, config.tracking_uri, f"fit {params.method} {params.target} "
                                                              f"(job {context.job_id[:8]})")
        context.set_mlflow_run(recorder.run_id, recorder.experiment_id)
    with context.ending(recorder):
        result = fit(config, store=recorder, tracker=recorder,
                     train_tracker=recorder.train_tracker if recorder else None, progress=context.progress,
                     say=context.logger.info, plan=plan)
    write_ladder(result, context.folder)
    context.logger.info("ladder:\n%s", format_ladder(result))
    if not result.met:
        run = f", MLflow run {recorder.run_id}" if recorder else ""
        raise JobFailure("target_not_met", f"{result.reason} (ladder: GET /jobs/{context.job_id}/artifacts/"
                         f"{LADDER_MARKDOWN} or {LADDER_JSON}{run})")
    return summary(result, context)


def summary(result, context: JobContext) -> dict[str, Any]:
    from model.fit.report import LADDER_JSON, LADDER_MARKDOWN

    root = context.storage.root.resolve()
    ladder = []
    for rung in result.to_dict()["ladder"]:
        path = rung.get("checkpoint")
        if path and Path(path).resolve().is_relative_to(root):
            rung["checkpoint"] = str(Path(path).resolve().relative_to(root))
        ladder.append(rung)
    info = result.to_dict()
    return {"family": info["family"], "scale": info["scale"], "target": info["target"],
            "target_description": info["target_description"], "met": info["met"], "chosen": info["chosen"],
            "reason": info["reason"], "registered": info.get("registered"), "alias": info.get("alias"),
            "timing": info.get("timing"), "fit_key": info.get("fit_key"), "ladder": ladder,
            "artifacts": {name: f"/jobs/{context.job_id}/artifacts/{name}" for name in (LADDER_JSON, LADDER_MARKDOWN)}}
