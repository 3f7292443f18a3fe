"""Speed against accuracy: evaluation reports (``model.evaluation.evaluate.evaluate``, one per scale) as one table and charts.

Rows (one per method, preset and scale), a Markdown table, a JSON document, and two charts: quality against time
per frame with each scale's Pareto front, and quality against cost. Point labels are placed so that none overlaps
another or leaves the plot (``model.evaluation.chart_labels``). A benchmark that timed fewer than
``MIN_TIMED_FRAMES`` frames per method says so in its table and chart. Details: docs/benchmark.md.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Sequence
from datetime import datetime, timezone
from pathlib import Path

from matplotlib.figure import Figure

from model.evaluation.chart_labels import PointLabel, freeze_layout, place_labels
from model.evaluation.evaluate import COLUMNS, UNCOUNTED_COST, run_summary
from model.evaluation.tables import cell, compact, table_row, table_rule, usable

# Quality measures in the rows: key, axis label, higher is better.
QUALITY = (("psnr", "PSNR dB (display-encoded) ↑", True), ("flip", "FLIP (display-encoded) ↓", False))
ROW_METRICS = ("psnr", "flip", "ssim", "smape", "temporal_error", "fvvdp_jod")
MARKERS = {1: "o", 2: "^", 4: "s"}
SCALE_NAMES = {1: "x1 (output = render resolution)", 2: "x2 (output 2x render resolution)", 4: "x4"}
FRONT_STYLES = {1: "--", 2: ":", 4: "-."}
# Fewer timed frames than this per method (after warm-up): the medians are noisy, and the table and chart say so.
MIN_TIMED_FRAMES = 5

BENCHMARK_JSON = "benchmark.json"
BENCHMARK_MARKDOWN = "benchmark.md"
QUALITY_SPEED_CHART = "quality_speed.png"
QUALITY_COST_CHART = "quality_cost.png"

Point = tuple[float | None, float | None]


# --------------------------------------------------------------------------------------------- Pareto

def pareto_front(points: Sequence[Point], *, x_lower_is_better: bool = True,
                 y_higher_is_better: bool = True) -> list[int]:
    """Indices of the points no other point dominates, ordered by x (ascending; ties by index).

    A point dominates another when it is at least as good on both x and y and strictly better on one. Equal
    points do not dominate each other, so duplicates are all on the front; a point equal on one axis and worse
    on the other is not. Points with a None or non-finite coordinate take no part.
    """
    sign_x = 1.0 if x_lower_is_better else -1.0
    sign_y = -1.0 if y_higher_is_better else 1.0
    # In (cost_x, cost_y), lower is better on both axes.
    costs = {i: (sign_x * float(x), sign_y * float(y)) for i, (x, y) in enumerate(points)
             if usable(x) and usable(y)}

    def dominated(i: int) -> bool:
        xi, yi = costs[i]
        return any(xj <= xi and yj <= yi and (xj < xi or yj < yi) for j, (xj, yj) in costs.items() if j != i)

    return sorted((i for i in costs if not dominated(i)), key=lambda i: (float(points[i][0]), i))


# ----------------------------------------------------------------------------------------------- rows

def _short_source(source: str) -> str:
    if source.startswith("models:/"):
        return source[len("models:/"):]
    parts = Path(source).parts
    return "/".join(parts[-2:]) if len(parts) > 1 else source


def rows_from_report(report: dict) -> list[dict]:
    """One row per method of one evaluation report (one scale), in the report's order."""
    sequences = report.get("sequences", [])
    inputs = sorted({s["input_resolution"] for s in sequences})
    outputs = sorted({s["output_resolution"] for s in sequences})
    rows = []
    for entry in report["methods"]:
        metrics = entry.get("metrics", {})
        counted = entry.get("method") not in UNCOUNTED_COST
        rows.append({
            "label": entry["label"], "source": entry.get("source", entry["label"]),
            "method": entry.get("method"), "preset": entry.get("preset"),
            "scale": int(entry.get("scale", report.get("scale", 1))), "learned": bool(entry.get("learned", False)),
            "cost_counted": counted, "params": entry.get("params") if counted else None,
            "flops_per_pixel": entry.get("flops_per_pixel") if counted else None,
            **{key: metrics.get(key) for key in ROW_METRICS},
            "ms_per_frame": entry.get("ms_per_frame"), "time_ratio_to_oidn": entry.get("time_ratio_to_oidn"),
            "frames_timed": (entry.get("timing") or {}).get("frames_timed"),
            "input_resolution": ", ".join(inputs), "output_resolution": ", ".join(outputs),
            "threads": report.get("threads"), "device": report.get("device"),
        })
    return rows


def _disambiguate(rows: list[dict]) -> None:
    """Two rows of one scale with the same label (two checkpoints of one preset) get their source appended."""
    by_key: dict[tuple[int, str], list[dict]] = {}
    for row in rows:
        by_key.setdefault((row["scale"], row["label"]), []).append(row)
    for group in by_key.values():
        if len(group) > 1:
            shorts = [_short_source(str(row["source"])) for row in group]
            distinct = len(set(shorts)) == len(shorts) and all(s != row["label"] for s, row in zip(shorts, group))
            for number, (row, short) in enumerate(zip(group, shorts), 1):
                row["label"] = f"{row['label']} ({short})" if distinct else f"{row['label']} #{number}"


def _mark_fronts(rows: list[dict]) -> None:
    """``row["pareto"]``: the quality measures (psnr, flip) for which the row is on its scale's time front."""
    for row in rows:
        row["pareto"] = []
    for scale in sorted({row["scale"] for row in rows}):
        group = [row for row in rows if row["scale"] == scale]
        for key, _, higher in QUALITY:
            points = [(row["ms_per_frame"], row[key]) for row in group]
            for index in pareto_front(points, y_higher_is_better=higher):
                group[index]["pareto"].append(key)


def benchmark_rows(reports: Iterable[dict]) -> list[dict]:
    """The rows of several reports (one per scale), by scale then ms per frame (untimed last), labels unique
    within a scale, each with the quality measures it is Pareto-optimal for against time (``pareto``)."""
    rows = [row for report in reports for row in rows_from_report(report)]
    _disambiguate(rows)
    _mark_fronts(rows)
    untimed = float("inf")
    return sorted(rows, key=lambda r: (r["scale"], r["ms_per_frame"] if usable(r["ms_per_frame"]) else untimed))


# ---------------------------------------------------------------------------------------------- table

TABLE_COLUMNS = ("psnr", "flip", "ssim", "temporal_error", "fvvdp_jod", "ms_per_frame", "time_ratio_to_oidn")
REFERENCE_HEADERS = {"time_ratio_to_oidn": "time / OIDN-high"}  # the benchmark's timing reference is OIDN-high


def scale_caption(report: dict) -> str:
    """What one scale's run measured: frames, resolutions, timing conditions, OIDN-high's time."""
    run = run_summary(report)
    reference_text = run["reference"] or "no timing reference (ratios not available)"
    vdp = report.get("fvvdp", {})
    vdp_text = ("JOD computed" if vdp.get("available") else
                "JOD skipped" if not vdp.get("enabled") else f"JOD unavailable: {vdp.get('reason')}")
    return (f"x{report['scale']}: {run['sequences']} sequences, {run['frames']} frames, input {run['inputs']} -> "
            f"output {run['outputs']}; "
            f"median ms/frame after {report['warmup_frames_per_sequence']} warm-up frames per sequence, "
            f"{report['threads']} threads, {report['device']}; {reference_text}; {vdp_text}")


def few_frames_note(rows: list[dict]) -> str | None:
    """A warning when some timed row's median comes from fewer than ``MIN_TIMED_FRAMES`` frames; else None."""
    counts: dict[int, int] = {}
    for row in rows:
        frames = row.get("frames_timed")
        if usable(row.get("ms_per_frame")) and isinstance(frames, int):
            counts[row["scale"]] = min(frames, counts.get(row["scale"], frames))
    few = {scale: frames for scale, frames in sorted(counts.items()) if frames < MIN_TIMED_FRAMES}
    if not few:
        return None
    where = ", ".join(f"{frames} at x{scale}" for scale, frames in few.items())
    return (f"timed on fewer than {MIN_TIMED_FRAMES} frames per method ({where}): the ms per frame and time ratios "
            f"are noise-prone; time more frames before relying on them")


def format_benchmark_table(rows: list[dict], reports: Iterable[dict] = (), skipped: Iterable[dict] = ()) -> str:
    """Markdown: one caption line per scale, then one row per method/preset/scale; ``front`` names the quality
    measures for which the row is on its scale's Pareto front against time."""
    reports = list(reports)
    lines = []
    if reports:
        first = reports[0]
        lines += [f"Benchmark on the {first['split']} split of {first['dataset']}.", ""]
        lines += [f"- {scale_caption(report)}" for report in reports]
        lines.append("")
    note = few_frames_note(rows)
    if note:
        lines += [f"Note: {note}.", ""]
    header = (["method", "scale", "params", "FLOPs/px"]
              + [REFERENCE_HEADERS.get(key, COLUMNS[key][0]) for key in TABLE_COLUMNS] + ["front"])
    lines += [table_row(header), table_rule("l" + "r" * (len(header) - 2) + "l")]
    for row in rows:
        cells = [row["label"], f"x{row['scale']}", compact(row["params"]), compact(row["flops_per_pixel"])]
        cells += [cell(row[key], COLUMNS[key][1]) for key in TABLE_COLUMNS]
        cells.append(", ".join(key.upper() for key in row.get("pareto", [])) or "")
        lines.append(table_row(cells))
    skipped = list(skipped)
    if skipped:
        lines += ["", "Not run:"] + [f"- {s['method']} at x{s['scale']}: {s['reason']}" for s in skipped]
    return "\n".join(lines)


def benchmark_document(reports: Iterable[dict], skipped: Iterable[dict] = ()) -> dict:
    """The JSON document: the rows, what was not run and why, and every scale's full evaluation report."""
    reports = list(reports)
    if not reports:
        raise ValueError("no evaluation reports to summarize")
    first = reports[0]
    return {
        "dataset": first["dataset"], "split": first["split"],
        "scales": [report["scale"] for report in reports],
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "threads": first["threads"], "device": first["device"],
        "learned_methods_rule": "learned methods come only from the checkpoints and model references given; "
                                "untrained presets are never benchmarked",
        "rows": benchmark_rows(reports),
        "skipped": list(skipped),
        "reports": {str(report["scale"]): report for report in reports},
    }


# --------------------------------------------------------------------------------------------- charts

def _colors(rows: list[dict]) -> dict[str, str]:
    """One colour per method (shared by its presets and both scales), in order of first appearance."""
    palette = [f"C{i}" for i in range(10)]
    names: list[str] = []
    for row in rows:
        name = row.get("method") or row["label"]
        if name not in names:
            names.append(name)
    return {name: palette[i % len(palette)] for i, name in enumerate(names)}


def _panel(axis, rows: list[dict], x_key: str, y_key: str, y_higher: bool, colors: dict[str, str],
           log_x: str, labels: list[PointLabel]) -> int:
    """Scatter ``rows`` on one axis (marker by scale), draw each scale's Pareto front, and add every point's label
    to ``labels`` (placed once the figure's layout is final: ``_label_points``).

    ``log_x``: "log" (positive values only) or "symlog" (zero allowed: parameter counts of filters).
    Returns the number of points drawn.
    """
    drawn = 0
    for scale in sorted({row["scale"] for row in rows}):
        group = [row for row in rows if row["scale"] == scale and usable(row[x_key]) and usable(row[y_key])
                 and (log_x != "log" or row[x_key] > 0)]
        if not group:
            continue
        marker = MARKERS.get(scale, "D")
        for row in group:
            axis.scatter([row[x_key]], [row[y_key]], marker=marker, s=36, zorder=3,
                         color=colors[row.get("method") or row["label"]], edgecolors="black", linewidths=0.4)
            labels.append(PointLabel(row[x_key], row[y_key], row["label"]))
        drawn += len(group)
        points = [(row[x_key], row[y_key]) for row in group]
        front = pareto_front(points, y_higher_is_better=y_higher)
        axis.plot([points[i][0] for i in front], [points[i][1] for i in front], drawstyle="steps-post",
                  linestyle=FRONT_STYLES.get(scale, "-"), color="gray", zorder=2, label=f"Pareto front x{scale}")
        # Legend entry for the marker (the points themselves are coloured by method).
        axis.scatter([], [], marker=marker, color="white", edgecolors="black", label=SCALE_NAMES.get(scale,
                                                                                                    f"x{scale}"))
    if log_x == "symlog":
        axis.set_xscale("symlog", linthresh=1.0)
    else:
        axis.set_xscale("log")
    axis.margins(x=0.12, y=0.08)  # room for labels beside the outermost points
    axis.grid(True, which="both", alpha=0.3)
    if drawn:
        axis.legend(fontsize=7, loc="best")
    return drawn


def _title(rows: list[dict], title: str | None) -> str:
    if title:
        return title
    scales = ", ".join(f"x{s}" for s in sorted({row["scale"] for row in rows}))
    return f"speed against accuracy ({scales})"


def _label_points(figure: Figure, labels: dict) -> None:
    """Place each axis's point labels (axis -> [PointLabel]) after the layout is fixed, where they fit."""
    renderer = freeze_layout(figure)
    for axis, points in labels.items():
        place_labels(axis, points, renderer)


def quality_speed_figure(rows: list[dict], title: str | None = None) -> Figure | None:
    """PSNR and FLIP (one panel each) against ms per frame (log scale); None when no row is timed and scored."""
    figure = Figure(figsize=(13, 5.5), layout="constrained")
    axes = figure.subplots(1, len(QUALITY))
    colors = _colors(rows)
    threads = sorted({str(row["threads"]) for row in rows if row.get("threads") is not None})
    devices = sorted({str(row["device"]) for row in rows if row.get("device")})
    conditions = ", ".join(filter(None, [f"{'/'.join(threads)} threads" if threads else "", "/".join(devices)]))
    drawn = 0
    labels: dict = {}
    for axis, (key, label, higher) in zip(axes, QUALITY):
        drawn += _panel(axis, rows, "ms_per_frame", key, higher, colors, "log", labels.setdefault(axis, []))
        axis.set_xlabel(f"ms per frame (median{', ' + conditions if conditions else ''}; log scale)")
        axis.set_ylabel(label)
    if not drawn:
        return None
    note = few_frames_note(rows)
    figure.suptitle(_title(rows, title) + (f"\n{note}" if note else ""), fontsize=11)
    _label_points(figure, labels)
    return figure


def quality_cost_figure(rows: list[dict], title: str | None = None) -> Figure | None:
    """PSNR and FLIP (rows) against parameters and FLOPs per output pixel (columns, symlog: filters have 0);
    methods whose cost is not counted (OIDN) are left out and named at the bottom. None when nothing is drawn."""
    figure = Figure(figsize=(13, 10), layout="constrained")
    axes = figure.subplots(len(QUALITY), 2)
    colors = _colors(rows)
    drawn = 0
    labels: dict = {}
    for line, (key, label, higher) in zip(axes, QUALITY):
        for axis, (x_key, x_label) in zip(line, (("params", "parameters (symlog)"),
                                                 ("flops_per_pixel", "FLOPs per output pixel (symlog)"))):
            drawn += _panel(axis, rows, x_key, key, higher, colors, "symlog", labels.setdefault(axis, []))
            axis.set_xlabel(x_label)
            axis.set_ylabel(label)
    if not drawn:
        return None
    figure.suptitle(_title(rows, title) + ": quality against size and compute", fontsize=11)
    uncounted = sorted({row["label"] for row in rows if not row.get("cost_counted", True)})
    if uncounted:
        figure.supxlabel(f"not shown: {', '.join(uncounted)} (network outside torch: parameters and FLOPs not "
                         f"counted)", fontsize=8, color="dimgray")
    _label_points(figure, labels)
    return figure


def save_figure(figure: Figure, path: str | os.PathLike, dpi: int = 100) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=dpi, format="png")
    return path


def write_quality_speed_chart(rows: list[dict], path: str | os.PathLike, title: str | None = None) -> Path | None:
    figure = quality_speed_figure(rows, title)
    return None if figure is None else save_figure(figure, path)


def write_quality_cost_chart(rows: list[dict], path: str | os.PathLike, title: str | None = None) -> Path | None:
    figure = quality_cost_figure(rows, title)
    return None if figure is None else save_figure(figure, path)


def write_benchmark(out_dir: str | os.PathLike, reports: Iterable[dict], skipped: Iterable[dict] = ()
                    ) -> dict[str, Path]:
    """Write benchmark.json, benchmark.md and the two charts into ``out_dir``; returns name -> path."""
    reports = list(reports)
    skipped = list(skipped)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    document = benchmark_document(reports, skipped)
    rows = document["rows"]
    files = {BENCHMARK_JSON: out / BENCHMARK_JSON, BENCHMARK_MARKDOWN: out / BENCHMARK_MARKDOWN}
    files[BENCHMARK_JSON].write_text(json.dumps(document, indent=2, allow_nan=False) + "\n")
    files[BENCHMARK_MARKDOWN].write_text(format_benchmark_table(rows, reports, skipped) + "\n")
    title = f"{document['dataset']} / {document['split']}"
    for name, writer in ((QUALITY_SPEED_CHART, write_quality_speed_chart),
                         (QUALITY_COST_CHART, write_quality_cost_chart)):
        path = writer(rows, out / name, title)
        if path is not None:
            files[name] = path
    return files
