"""The ``evaluate`` and ``benchmark`` jobs: model.evaluation.evaluate's protocol on a stored dataset split.

Both write ``report.json`` (the full report) and ``report.md`` (its table) into the job folder and summarize the
methods in the job result; ``benchmark`` defaults its method list to the non-learned baselines and OIDN's three
presets, refuses learned registry presets (untrained weights: learned methods come only as model references or
checkpoints), and also draws ``quality_speed.png`` with ``model.evaluation.benchmark`` (PSNR and FLIP against time per
frame, log scale, Pareto front; the chart ``denoiser benchmark`` draws, served at GET /jobs/{id}/chart.png). With
``track`` the run goes to MLflow (experiment ``denoiser-evaluation``): parameters, one metric per method and
measure, the files as artifacts; and a registered model version that was evaluated gets its measurements as
version tags (``ms_per_frame``, ``metric.<name>``), which GET /models shows.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from core.jobs.evaluate import default_methods
from core.jobs.files import CHART, REPORT_JSON, REPORT_MARKDOWN
from core.jobs.methods import is_model_ref, runnable
from core.jobs.specs import BenchmarkParams, EvaluateParams
from core.jobs.checks import open_dataset, split_sequences
from workers.tasks.context import JobContext

EXPERIMENT = "denoiser-evaluation"
ARTIFACTS = (REPORT_JSON, REPORT_MARKDOWN, CHART)
SUMMARY_KEYS = ("label", "source", "method", "preset", "scale", "params", "flops_per_pixel", "ms_per_frame",
                "time_ratio_to_oidn")


def run(context: JobContext) -> dict[str, Any]:
    from model.evaluation.evaluate import TIMING_REFERENCE, evaluate, format_table

    model = BenchmarkParams if context.record["kind"] == "benchmark" else EvaluateParams
    params = model.model_validate(context.params)
    methods = list(params.methods or default_methods(params.scale))
    dataset_dir = context.storage.dataset(params.dataset)
    sequences = split_sequences(open_dataset(context.storage, params.dataset), params.dataset, params.split,
                                params.scale)
    timed_separately = params.oidn_timing and TIMING_REFERENCE not in methods
    total = (len(methods) + int(timed_separately)) * len(sequences)
    runs = 0

    def say(message: str) -> None:
        nonlocal runs, total
        total = max(total, runs + 1)
        context.progress(runs, total, message)
        runs += 1

    tracker = _start_tracking(context, params, methods) if params.track else None
    try:
        report = evaluate(dataset_dir, [runnable(m, context.storage) for m in methods], split=params.split,
                          scale=params.scale, frame_limit=params.frames, threads=params.threads, vdp=params.vdp,
                          timing_reference=TIMING_REFERENCE if params.oidn_timing else None,
                          device=context.torch_device, progress=say,
                          inference_forms=context.settings.inference_forms)
        context.progress(total, total, "writing the report")
        for entry, text in zip(report["methods"], methods):
            entry["source"] = text  # the reference as given, not the cached checkpoint's path
        report["dataset"] = params.dataset
        files = _write_files(context.folder, report, format_table(report), chart=context.record["kind"] ==
                             "benchmark")
        if tracker is not None:
            _log_results(tracker, report, files)
            tracker.finish("FINISHED")
    except BaseException:
        if tracker is not None:
            tracker.finish("KILLED" if context.cancelled.is_set() else "FAILED")
        raise
    if params.track:
        _tag_registered_versions(context, report, f"{params.dataset}/{params.split}")
    return summary(context.job_id, report, files)


def summary(job_id: str, report: dict, files: dict[str, Path]) -> dict[str, Any]:
    reference = report["timing_reference"]
    return {
        "dataset": report["dataset"], "split": report["split"], "scale": report["scale"],
        "sequences": len(report["sequences"]), "frames": sum(s["frames"] for s in report["sequences"]),
        "threads": report["threads"], "device": report["device"],
        "timing_reference": None if reference is None else {"label": reference["label"],
                                                            "ms_per_frame": reference["ms_per_frame"]},
        "methods": [{**{key: entry.get(key) for key in SUMMARY_KEYS}, "metrics": entry["metrics"]}
                    for entry in report["methods"]],
        "table": files["table"],
        "artifacts": {name: f"/jobs/{job_id}/artifacts/{name}" for name in files if name in ARTIFACTS},
    }


def _write_files(folder: Path, report: dict, table: str, chart: bool) -> dict[str, Any]:
    (folder / REPORT_JSON).write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
    (folder / REPORT_MARKDOWN).write_text(table + "\n")
    files: dict[str, Any] = {REPORT_JSON: folder / REPORT_JSON, REPORT_MARKDOWN: folder / REPORT_MARKDOWN,
                             "table": table}
    if chart:
        path = quality_speed_chart(report, folder / CHART)
        if path is not None:
            files[CHART] = path
    return files


def quality_speed_chart(report: dict, path: Path) -> Path | None:
    """PSNR and FLIP against ms per frame (log scale), Pareto front, every point labelled (model.evaluation.benchmark);
    None when no method was both timed and scored."""
    from model.evaluation.benchmark import benchmark_rows, write_quality_speed_chart

    title = f"{report['dataset']} / {report['split']}, scale {report['scale']}"
    return write_quality_speed_chart(benchmark_rows([report]), path, title)


# ---------------------------------------------------------------------------------------------- MLflow

def _metric_key(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_\-. :/]", "_", text)


def _start_tracking(context: JobContext, params: EvaluateParams, methods: list[str]):
    from core.tracking import MLflowTracker

    tracker = MLflowTracker(context.settings.resolved_tracking_uri(), EXPERIMENT,
                            run_name=f"{context.record['kind']} {params.dataset}/{params.split} "
                                     f"(job {context.job_id[:8]})")
    tracker.start({"kind": context.record["kind"], "job_id": context.job_id, "dataset": params.dataset,
                   "split": params.split, "scale": params.scale, "methods": ",".join(methods),
                   "frames": params.frames, "vdp": params.vdp, "device": context.torch_device})
    context.set_mlflow_run(tracker.run_id, getattr(tracker, "_experiment_id", None))
    tracker.log_dataset(context.storage.dataset(params.dataset), "evaluation")
    return tracker


def _log_results(tracker, report: dict, files: dict[str, Any]) -> None:
    metrics: dict[str, float] = {}
    for entry in report["methods"]:
        name = _metric_key(entry["source"])
        values = {**entry["metrics"], "ms_per_frame": entry["ms_per_frame"],
                  "time_ratio_to_oidn": entry["time_ratio_to_oidn"]}
        metrics.update({f"{name}/{key}": value for key, value in values.items() if value is not None})
    tracker.log_metrics(metrics, step=0)
    for name, path in files.items():
        if name in ARTIFACTS:
            tracker.client.log_artifact(tracker.run_id, str(path))


def _tag_registered_versions(context: JobContext, report: dict, evaluated_on: str) -> None:
    """Measurements of evaluated registered versions as version tags (best effort: only metadata is at stake)."""
    refs = [entry for entry in report["methods"] if is_model_ref(entry["source"])]
    if not refs:
        return
    try:
        from core.registry import get_registry

        registry = get_registry()
        for entry in refs:
            version = registry.resolve(entry["source"]).info
            tags = {f"metric.{key}": f"{value:.6g}" for key, value in entry["metrics"].items() if value is not None}
            if entry["ms_per_frame"] is not None:
                tags["ms_per_frame"] = f"{entry['ms_per_frame']:.6g}"
            tags["evaluated_on"] = evaluated_on
            for key, value in tags.items():
                registry.client.set_model_version_tag(version.name, version.version, key, value)
    except Exception:
        context.logger.warning("could not tag the evaluated model versions", exc_info=True)
