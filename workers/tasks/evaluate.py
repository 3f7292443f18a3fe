"""The ``evaluate`` and ``benchmark`` jobs: model.evaluation.evaluate's protocol on a stored dataset split.

A run at one scale writes ``report.json`` (the full report) and ``report.md`` (its table) into the job folder and
summarizes the methods in the job result. A benchmark (its methods and scales: ``core.jobs.evaluate``) also writes
what ``denoiser benchmark`` writes (``model.evaluation.benchmark.write_benchmark``): ``benchmark.json``,
``benchmark.md``, ``quality_speed.png`` (served at GET /jobs/{id}/chart.png) and ``quality_cost.png``. With
``track`` the run goes to MLflow (experiment ``denoiser-evaluation``): parameters, one metric per method and
measure, the files as artifacts; and a registered model version that was evaluated gets its measurements as
version tags (``ms_per_frame``, ``metric.<name>``), which GET /models shows. An evaluate job also draws one
side-by-side picture per sequence of its last evaluated frame (input, each method, reference:
``comparison_<sequence>.png``, ``model.evaluation.compare``), served and logged with the other files.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from core.jobs.checks import open_dataset, split_sequences
from core.jobs.evaluate import benchmark_scales, planned_methods, runs_at
from core.jobs.files import BENCHMARK_FILES, CHART, COMPARISON, REPORT_JSON, REPORT_MARKDOWN, comparison_name
from core.jobs.methods import is_model_ref, runnable
from core.jobs.specs import BenchmarkParams, EvaluateParams
from workers.tasks.context import JobContext

EXPERIMENT = "denoiser-evaluation"
ARTIFACTS = (REPORT_JSON, REPORT_MARKDOWN, CHART, *BENCHMARK_FILES)
SUMMARY_KEYS = ("label", "source", "method", "preset", "scale", "params", "flops_per_pixel", "ms_per_frame",
                "time_ratio_to_oidn")


def run(context: JobContext) -> dict[str, Any]:
    from model.evaluation.evaluate import TIMING_REFERENCE, evaluate, format_table

    benchmark = context.record["kind"] == "benchmark"
    params = (BenchmarkParams if benchmark else EvaluateParams).model_validate(context.params)
    scales = benchmark_scales(params.scale)
    methods = planned_methods(params)
    # At both scales a method runs at those it can (the check made sure it runs at one at least).
    plan = {scale: [m for m in methods if len(scales) == 1 or runs_at(m, scale, context.storage)]
            for scale in scales}
    skipped = [{"method": m, "scale": scale, "reason": f"{m} does not run at scale {scale}"}
               for scale, running in plan.items() for m in methods if m not in running]
    dataset_dir = context.storage.dataset(params.dataset)
    sequences = {scale: split_sequences(open_dataset(context.storage, params.dataset), params.dataset,
                                        params.split, scale) for scale in scales}
    timed_separately = {scale: params.oidn_timing and TIMING_REFERENCE not in plan[scale] for scale in scales}
    total = sum((len(plan[s]) + int(timed_separately[s])) * len(sequences[s]) for s in scales)
    runs = 0

    def say(message: str) -> None:
        nonlocal runs, total
        total = max(total, runs + 1)
        context.progress(runs, total, message)
        runs += 1

    tracker = _start_tracking(context, params, methods) if params.track else None
    with context.ending(tracker):
        reports = []
        pictures: dict[str, Path] = {}
        for scale in scales:
            if not plan[scale]:
                continue
            draw = None if benchmark else _comparison_drawer(context.folder, pictures,
                                                             scale if len(scales) > 1 else None)
            report = evaluate(dataset_dir, [runnable(m, context.storage) for m in plan[scale]], split=params.split,
                              scale=scale, frame_limit=params.frames, threads=params.threads, vdp=params.vdp,
                              timing_reference=TIMING_REFERENCE if params.oidn_timing else None,
                              device=context.torch_device, progress=say,
                              inference_forms=context.settings.inference_forms, last_outputs=draw)
            for entry, text in zip(report["methods"], plan[scale]):
                entry["source"] = text  # the reference as given, not the cached checkpoint's path
            report["dataset"] = params.dataset
            reports.append(report)
        context.progress(total, total, "writing the report")
        files = {**_write_files(context.folder, reports, format_table, skipped, benchmark), **pictures}
        if tracker is not None:
            _log_results(tracker, reports, files)
    if params.track:
        for report in reports:
            _tag_registered_versions(context, report, f"{params.dataset}/{params.split}")
    if len(reports) == 1:
        return summary(context.job_id, reports[0], files)
    return {"dataset": params.dataset, "split": params.split, "scales": [r["scale"] for r in reports],
            "runs": [{key: value for key, value in summary(context.job_id, r, {}).items()
                      if key not in ("table", "artifacts")} for r in reports],
            "skipped": skipped, "table": files["table"], "artifacts": _artifact_urls(context.job_id, files)}


def summary(job_id: str, report: dict, files: dict[str, Any]) -> dict[str, Any]:
    reference = report["timing_reference"]
    return {
        "dataset": report["dataset"], "split": report["split"], "scale": report["scale"],
        "sequences": len(report["sequences"]), "frames": sum(s["frames"] for s in report["sequences"]),
        "threads": report["threads"], "device": report["device"],
        "timing_reference": None if reference is None else {"label": reference["label"],
                                                            "ms_per_frame": reference["ms_per_frame"]},
        "methods": [{**{key: entry.get(key) for key in SUMMARY_KEYS}, "metrics": entry["metrics"]}
                    for entry in report["methods"]],
        "table": files.get("table"),
        "artifacts": _artifact_urls(job_id, files),
    }


def _artifact_urls(job_id: str, files: dict[str, Any]) -> dict[str, str]:
    return {name: f"/jobs/{job_id}/artifacts/{name}" for name in files if _is_artifact(name)}


def _is_artifact(name: str) -> bool:
    return name in ARTIFACTS or bool(COMPARISON.match(name))


def _comparison_drawer(folder: Path, pictures: dict[str, Path], scale: int | None):
    """The evaluation's ``last_outputs`` callback: each sequence's picture into the job folder, noted in
    ``pictures`` (name: path)."""
    from model.evaluation.compare import last_frame_panels, save_comparison

    def draw(sequence, outputs) -> None:
        name = comparison_name(sequence.name, scale)
        frame = len(sequence.frames) - 1
        pictures[name] = save_comparison(last_frame_panels(sequence, outputs), folder / name,
                                         title=f"{sequence.name}, frame {frame} (x{sequence.scale})")

    return draw


def _write_files(folder: Path, reports: list[dict], format_table, skipped: list[dict],
                 benchmark: bool) -> dict[str, Any]:
    """One scale: its report (report.json, report.md); a benchmark also writes the benchmark table and charts of
    every scale it ran (``model.evaluation.benchmark.write_benchmark``, as ``denoiser benchmark`` does)."""
    files: dict[str, Any] = {}
    if len(reports) == 1:
        report, table = reports[0], format_table(reports[0])
        (folder / REPORT_JSON).write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
        (folder / REPORT_MARKDOWN).write_text(table + "\n")
        files.update({REPORT_JSON: folder / REPORT_JSON, REPORT_MARKDOWN: folder / REPORT_MARKDOWN, "table": table})
    if benchmark:
        from model.evaluation.benchmark import BENCHMARK_MARKDOWN, write_benchmark

        written = write_benchmark(folder, reports, skipped)
        files.update(written)
        files.setdefault("table", written[BENCHMARK_MARKDOWN].read_text().rstrip())
    return files


# ---------------------------------------------------------------------------------------------- MLflow

def metric_key(text: str) -> str:
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


def _log_results(tracker, reports: list[dict], files: dict[str, Any]) -> None:
    metrics: dict[str, float] = {}
    for report in reports:
        prefix = f"x{report['scale']}/" if len(reports) > 1 else ""
        for entry in report["methods"]:
            name = prefix + metric_key(entry["source"])
            values = {**entry["metrics"], "ms_per_frame": entry["ms_per_frame"],
                      "time_ratio_to_oidn": entry["time_ratio_to_oidn"]}
            metrics.update({f"{name}/{key}": value for key, value in values.items() if value is not None})
    tracker.log_metrics(metrics, step=0)
    for name, path in files.items():
        if _is_artifact(name):
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
