"""The stability suite's report: Markdown (worst scenario per method, PSNR, drops, ghosting, every metric,
sanitized inputs), the charts (per-frame curves, the drop heat map) and the files ``stability.json`` and
``stability.md``. The suite itself, its scenarios and scoring: ``model.evaluation.stability``; definitions: docs/stability.md.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from model.evaluation.stability import MIN_DROP_DB
from model.ops.output_bound import OUTPUT_BOUND_FACTOR
from model.evaluation.tables import cell, cell_text, table_row, table_rule

__all__ = ["format_markdown", "write_report", "curves_chart", "drop_chart", "REPORT_JSON", "REPORT_MARKDOWN"]


def _worst_text(entry: dict) -> tuple[str, str]:
    worst = entry["worst"]
    if worst["scenario"] is None:
        return "none", f"every drop < {MIN_DROP_DB:g} dB"
    if worst["failed"]:
        return worst["scenario"], f"FAILED: {cell_text(worst['reason'])}"
    return worst["scenario"], (f"{worst['drop_db']:.2f} dB below its median gain (gain {worst['gain_db']:+.2f} dB, "
                               f"median {entry['median_gain_db']:+.2f} dB; PSNR {worst['psnr']:.2f} dB)")


def _worst_output_ratio(entry: dict) -> float | None:
    ratios = [run["output_ratio"] for run in entry["scenarios"].values() if run.get("output_ratio") is not None]
    return max(ratios) if ratios else None  # None: a report written before the ratio was recorded


def _run_cell(run: dict, key: str, fmt: str) -> str:
    return "FAIL" if run["status"] == "failed" else cell(run.get(key), fmt)


def format_markdown(report: dict, charts: dict[str, str] | None = None) -> str:
    """The report as Markdown: the worst scenario per method, PSNR and drop per scenario, every metric, the
    sanitized input counts, and links to the charts (``charts``: name -> path relative to the report)."""
    charts = charts or {}
    scenarios = report["scenarios"]
    methods = report["methods"]
    vdp = report["fvvdp"]
    conditions = (f"{len(scenarios)} scenarios, input {report['input_resolution']} -> output "
                  f"{report['output_resolution']} (scale {report['scale']}), {report['device']}, "
                  f"torch threads: {report['threads']}" + (f", data {report['data']}" if report.get("data") else "")
                  + ("; FovVideoVDP skipped (--vdp runs it)" if not vdp["enabled"] else
                     "" if vdp["available"] else f"; FovVideoVDP unavailable: {vdp['reason']}"))
    lines = ["# Stability suite", "", conditions, "", "## Where each method fails worst", "",
             f"Definition: {report['definition']}", "",
             "worst output / input: the largest ratio, over the scenarios and frames it completed, of its brightest "
             "output pixel to the frame's brightest input value (the output bound keeps it at or below "
             f"{OUTPUT_BOUND_FACTOR:g}; docs/methods.md).", "",
             table_row(["method", "worst scenario", "by how much", "failures", "worst output / input"]),
             table_rule("llllr")]
    for entry in methods:
        scenario, how = _worst_text(entry)
        failures = ", ".join(f["scenario"] for f in entry["failures"]) or "none"
        lines.append(table_row([entry["label"], scenario, how, failures, cell(_worst_output_ratio(entry), "{:.3g}")]))

    labels = [report["input"][scenarios[0]["name"]]["label"]] + [e["label"] for e in methods]
    lines += ["", "## PSNR per scenario (dB, display-encoded; FAIL: error or non-finite output)", "",
              table_row(["scenario"] + labels), table_rule("l" + "r" * len(labels))]
    for scenario in scenarios:
        name = scenario["name"]
        lines.append(table_row([name, _run_cell(report["input"][name], "psnr", "{:.2f}")]
                               + [_run_cell(e["scenarios"][name], "psnr", "{:.2f}") for e in methods]))
    lines += ["", "## Drop per scenario (dB: median gain minus gain; higher is worse, negative is better than usual)",
              "", table_row(["scenario"] + [e["label"] for e in methods]), table_rule("l" + "r" * len(methods))]
    for scenario in scenarios:
        name = scenario["name"]
        lines.append(table_row([name] + [_run_cell(e["scenarios"][name], "drop_db", "{:+.2f}") for e in methods]))

    lines += _ghosting_lines(report, charts)

    lines += ["", "## Every metric per scenario", "",
              "vs clean: PSNR minus the method's PSNR on `clean` (derived scenarios only; exposure and first frames "
              "compare other references or fewer frames, so read them with the gain)."]
    for scenario in scenarios:
        name = scenario["name"]
        cuts = f", cut before frame {', '.join(map(str, scenario['camera_cuts']))}" if scenario["camera_cuts"] else ""
        lines += ["", f"### {name}", "",
                  f"{scenario['description']} (from `{scenario['source']}`, {scenario['frames']} frames{cuts})", "",
                  table_row(["method", "PSNR ↑", "SSIM ↑", "FLIP ↓", "SMAPE ↓", "temporal ↓", "ghost ↓", "JOD ↑",
                             "gain dB", "vs clean dB"]), table_rule("l" + "r" * 9)]
        for entry in methods:
            run = entry["scenarios"][name]
            if run["status"] == "failed":
                lines.append(f"| {entry['label']} | FAILED: {cell_text(run['error'])} |" + " |" * 9)
                continue
            cells = [cell(run["psnr"], "{:.2f}"), cell(run["ssim"], "{:.4f}"), cell(run["flip"], "{:.4f}"),
                     cell(run["smape"], "{:.4f}"), cell(run["temporal_error"], "{:.5f}"),
                     cell(run.get("ghost_error"), "{:.4f}"), cell(run.get("fvvdp_jod"), "{:.2f}"),
                     cell(run["gain_db"], "{:+.2f}"), cell(run["vs_clean_db"], "{:+.2f}")]
            lines.append(table_row([entry["label"]] + cells))

    lines += ["", "## Sanitized inputs", "",
              "Pixels repaired by `model.io.sanitize.sanitize_frame` before any method saw them (summed over frames; "
              "the same for every method).", "", table_row(["scenario", "repaired pixels", "per buffer"]),
              table_rule("lrl")]
    for scenario in scenarios:
        counts = scenario["sanitized"] or {"total": 0, "non_finite": {}, "out_of_range": {}}
        parts = [f"{b}: {n} non-finite" for b, n in counts["non_finite"].items()]
        parts += [f"{b}: {n} out of range" for b, n in counts["out_of_range"].items()]
        lines.append(table_row([scenario["name"], counts["total"], "; ".join(parts) or "-"]))

    if charts:
        lines += ["", "## Charts", ""]
        if "psnr_curves" in charts:
            lines += ["PSNR of every frame, one line per method, the noisy input dashed (dotted lines: camera cuts):",
                      "", f"![per-frame PSNR]({charts['psnr_curves']})", ""]
        if "psnr_drop" in charts:
            lines += ["Drop per method and scenario (red: worse than the method's median):", "",
                      f"![drop per scenario]({charts['psnr_drop']})", ""]
        per_scenario = [f"[{s['name']}]({charts['curve:' + s['name']]})" for s in scenarios
                        if "curve:" + s["name"] in charts]
        if per_scenario:
            lines.append("One chart per scenario: " + ", ".join(per_scenario) + ".")
    if report["missing_scenarios"]:
        lines += ["", "## Not run", ""] + [f"- {m['name']}: {m['reason']}" for m in report["missing_scenarios"]]
    return "\n".join(lines) + "\n"


def _ghosting_lines(report: dict, charts: dict[str, str]) -> list[str]:
    """The ghosting section: ghost error and ghost PSNR per scenario with a trail, who ghosts least, the chart."""
    ghosting, methods = report["ghosting"], report["methods"]
    with_trail = [s for s in report["scenarios"] if s["trail"]["frames"]]
    lines = ["", "## Ghosting (error inside the trail region; lower is better)", "",
             f"Definition: {ghosting['definition']}", ""]
    if ghosting["temporal"]:
        lines.append("Temporal methods (they carry history from frame to frame): "
                     + ", ".join(ghosting["temporal"]) + ".")
    else:
        lines.append("No temporal method ran (per-frame methods cannot ghost).")
    if ghosting["least"] is not None:
        others = "; ".join(f"{label} {value:.4f}" for label, value in ghosting["mean_error"].items()
                           if label != ghosting["least"])
        lines.append(f"Ghosts least among them: **{ghosting['least']}** (mean ghost error "
                     f"{ghosting['mean_error'][ghosting['least']]:.4f} over {len(ghosting['common_scenarios'])} "
                     f"scenarios with a trail" + (f"; {others}" if others else "") + ").")
    without = [s["name"] for s in report["scenarios"] if not s["trail"]["frames"]]
    if without:
        lines.append("No trail (nothing changed beyond what the motion explains): " + ", ".join(without) + ".")
    if not with_trail:
        return lines
    labels = [report["input"][with_trail[0]["name"]]["label"]] + [e["label"] for e in methods]
    lines += ["", "Ghost error (mean display-encoded absolute error in the trail, 0..1; lower is better):", "",
              table_row(["scenario", "trail frames", "trail pixels"] + labels + ["least (temporal)"]),
              table_rule("lrr" + "r" * len(labels) + "l")]
    for scenario in with_trail:
        name = scenario["name"]
        cells = [_run_cell(report["input"][name], "ghost_error", "{:.4f}")]
        cells += [_run_cell(e["scenarios"][name], "ghost_error", "{:.4f}") for e in methods]
        trail = scenario["trail"]
        lines.append(table_row([name, f"{trail['frames']}/{scenario['frames']}", f"{trail['coverage']:.1%}"] + cells
                               + [ghosting["by_scenario"].get(name) or "-"]))
    lines += ["", "Ghost PSNR (dB in the trail; higher is better):", "",
              table_row(["scenario"] + labels), table_rule("l" + "r" * len(labels))]
    for scenario in with_trail:
        name = scenario["name"]
        cells = [_run_cell(report["input"][name], "ghost_psnr", "{:.2f}")]
        cells += [_run_cell(e["scenarios"][name], "ghost_psnr", "{:.2f}") for e in methods]
        lines.append(table_row([name] + cells))
    if "ghost_curves" in charts:
        lines += ["", "Ghost error of every frame (gaps: no trail yet), one line per method, the noisy input dashed:",
                  "", f"![ghost error per frame]({charts['ghost_curves']})"]
    return lines


# What a curves chart plots: the per-frame values' key in a run, and the y-axis label.
CURVES = {"psnr": ("per_frame_psnr", "PSNR dB"),
          "ghost_error": ("per_frame_ghost_error", "ghost error (lower is better)")}


def _plot_curves(axis, report: dict, scenario: dict, key: str = "per_frame_psnr", ylabel: str = "PSNR dB") -> None:
    from matplotlib.ticker import MaxNLocator

    def numbers(values: list[float | None]) -> list[float]:
        return [math.nan if v is None else v for v in values]  # frames without a value (no trail) leave a gap

    name = scenario["name"]
    source = report["input"][name]
    if source.get(key):
        values = numbers(source[key])
        axis.plot(range(len(values)), values, linestyle="--", color="gray", label=source["label"])
    for entry in report["methods"]:
        run = entry["scenarios"][name]
        if run["status"] == "ok":
            values = numbers(run[key])
            axis.plot(range(len(values)), values, marker="o", markersize=2.5, linewidth=1.2, label=entry["label"])
        else:
            axis.plot([], [], linestyle="none", label=f"{entry['label']} (failed)")
    for cut in scenario["camera_cuts"]:
        axis.axvline(cut - 0.5, color="black", linestyle=":", linewidth=0.8)
    axis.set_title(name, fontsize=9)
    axis.xaxis.set_major_locator(MaxNLocator(integer=True))
    axis.set_xlabel("frame", fontsize=8)
    axis.set_ylabel(ylabel, fontsize=8)
    axis.tick_params(labelsize=7)
    axis.grid(True, alpha=0.3)


def curves_chart(report: dict, path: Path, scenario: str | None = None, metric: str = "psnr") -> Path:
    """Per-frame PSNR (``metric`` "psnr") or ghost error ("ghost_error", scenarios with a trail only): one panel
    per scenario (or only ``scenario``), one line per method (matplotlib Figure)."""
    from matplotlib.figure import Figure

    key, ylabel = CURVES[metric]
    scenarios = [s for s in report["scenarios"] if (scenario is None or s["name"] == scenario)
                 and (metric != "ghost_error" or s["trail"]["frames"])]
    if not scenarios:
        raise ValueError(f"no scenario to chart {metric} for")
    columns = min(4, len(scenarios))
    rows = math.ceil(len(scenarios) / columns)
    legend_inches = 0.45
    figure = Figure(figsize=(3.6 * columns, 2.7 * rows + legend_inches))
    axes = figure.subplots(rows, columns, squeeze=False)
    for index, entry in enumerate(scenarios):
        _plot_curves(axes[index // columns][index % columns], report, entry, key, ylabel)
    for index in range(len(scenarios), rows * columns):
        axes[index // columns][index % columns].set_axis_off()
    handles, labels = axes[0][0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="lower center", ncol=min(len(labels), 5), fontsize=8, frameon=False)
    figure.tight_layout(rect=(0, legend_inches / (2.7 * rows + legend_inches), 1, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    return path


def drop_chart(report: dict, path: Path) -> Path:
    """Heat map of the drop (dB) per method (rows) and scenario (columns); failures marked."""
    import numpy as np
    from matplotlib.figure import Figure

    names = [s["name"] for s in report["scenarios"]]
    methods = report["methods"]
    values = np.full((len(methods), len(names)), np.nan)
    for row, entry in enumerate(methods):
        for column, name in enumerate(names):
            drop = entry["scenarios"][name].get("drop_db")
            values[row, column] = np.nan if drop is None else drop
    limit = max(1.0, float(np.nanmax(np.abs(values))) if np.isfinite(values).any() else 1.0)
    figure = Figure(figsize=(1.0 + 0.75 * len(names), 1.2 + 0.45 * len(methods)))
    axis = figure.subplots()
    image = axis.imshow(np.nan_to_num(values, nan=0.0), cmap="RdBu_r", vmin=-limit, vmax=limit, aspect="auto")
    for row, entry in enumerate(methods):
        for column, name in enumerate(names):
            failed = entry["scenarios"][name]["status"] == "failed"
            value = values[row, column]
            text = "FAIL" if failed else ("-" if np.isnan(value) else f"{value + 0.0:+.1f}")
            strong = not np.isnan(value) and abs(value) > 0.6 * limit
            axis.text(column, row, text, ha="center", va="center", fontsize=7,
                      color="darkred" if failed else ("white" if strong else "black"),
                      fontweight="bold" if failed else "normal")
    axis.set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=8)
    axis.set_yticks(range(len(methods)), [e["label"] for e in methods], fontsize=8)
    axis.set_title("drop = median gain - gain (dB); higher is worse", fontsize=9)
    figure.colorbar(image, ax=axis, fraction=0.03)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    return path


REPORT_JSON = "stability.json"
REPORT_MARKDOWN = "stability.md"


def write_report(report: dict, out: str | os.PathLike, per_scenario_charts: bool = True) -> dict[str, Path]:
    """Write ``stability.json``, the charts (``psnr_curves.png``, ``psnr_drop.png``, ``ghost_curves.png`` when a
    scenario has a trail, ``curves/NAME.png``) and ``stability.md`` into the folder ``out``; returns name -> path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"json": out / REPORT_JSON, "markdown": out / REPORT_MARKDOWN,
             "psnr_curves": curves_chart(report, out / "psnr_curves.png"),
             "psnr_drop": drop_chart(report, out / "psnr_drop.png")}
    if any(s["trail"]["frames"] for s in report["scenarios"]):
        files["ghost_curves"] = curves_chart(report, out / "ghost_curves.png", metric="ghost_error")
    if per_scenario_charts:
        for scenario in report["scenarios"]:
            files["curve:" + scenario["name"]] = curves_chart(report, out / "curves" / f"{scenario['name']}.png",
                                                             scenario["name"])
    files["json"].write_text(json.dumps(report, indent=2, allow_nan=False) + "\n")
    relative = {name: path.relative_to(out).as_posix() for name, path in files.items() if path.suffix == ".png"}
    files["markdown"].write_text(format_markdown(report, relative))
    return files

