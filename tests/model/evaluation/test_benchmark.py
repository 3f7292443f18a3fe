"""model.evaluation.benchmark: the Pareto front, rows and table from evaluation reports, the charts' points and labels."""

from __future__ import annotations

import json
import math

import pytest

from model.evaluation.benchmark import (QUALITY_COST_CHART, QUALITY_SPEED_CHART, benchmark_document, benchmark_rows,
                             format_benchmark_table, pareto_front, quality_cost_figure, quality_speed_figure,
                             rows_from_report, write_benchmark)
from matplotlib.text import Text

from model.evaluation.chart_labels import freeze_layout

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# --------------------------------------------------------------------------------------------- Pareto

def test_pareto_front_time_lower_quality_higher():
    points = [(1.0, 10.0), (2.0, 12.0), (3.0, 11.0), (4.0, 15.0), (0.5, 5.0), (5.0, 14.0)]
    # (3, 11) is beaten by (2, 12); (5, 14) by (4, 15). The front is ordered by x.
    assert pareto_front(points) == [4, 0, 1, 3]


def test_pareto_front_ties():
    # Equal x: only the better y survives. Equal y: only the smaller x. Identical points: neither dominates.
    assert pareto_front([(1.0, 10.0), (1.0, 9.0)]) == [0]
    assert pareto_front([(2.0, 10.0), (1.0, 10.0)]) == [1]
    assert pareto_front([(1.0, 10.0), (1.0, 10.0), (2.0, 11.0)]) == [0, 1, 2]
    assert pareto_front([(1.0, 10.0), (1.0, 10.0), (0.5, 10.0)]) == [2]


def test_pareto_front_both_directions():
    flip = [(1.0, 0.20), (2.0, 0.10), (3.0, 0.15), (0.5, 0.30)]  # lower FLIP is better
    assert pareto_front(flip, y_higher_is_better=False) == [3, 0, 1]
    assert pareto_front(flip) == [3]  # read as "higher is better", the fastest point is also the best
    throughput = [(10.0, 1.0), (20.0, 0.5), (5.0, 2.0)]  # x higher is better, y lower is better
    assert pareto_front(throughput, x_lower_is_better=False, y_higher_is_better=False) == [1]
    assert pareto_front(throughput, x_lower_is_better=False) == [2, 0, 1]


def test_pareto_front_skips_missing_values():
    assert pareto_front([]) == []
    assert pareto_front([(None, 1.0), (1.0, math.nan), (2.0, 3.0), (math.inf, 9.0)]) == [2]


# ------------------------------------------------------------------------------------------ reports

def entry(label: str, method: str, preset: str, scale: int, params: int, flops: float, psnr: float | None,
          flip: float | None, ms: float | None, ratio: float | None, source: str | None = None) -> dict:
    return {"label": label, "source": source or label, "method": method, "preset": preset, "scale": scale,
            "learned": params > 0, "params": params, "flops_per_pixel": flops,
            "metrics": {"psnr": psnr, "ssim": 0.5, "flip": flip, "smape": 0.1, "temporal_error": 0.02,
                        "fvvdp_jod": None},
            "sequences": {}, "timing": {}, "ms_per_frame": ms, "time_ratio_to_oidn": ratio}


def report(scale: int, entries: list[dict], reference_ms: float = 80.0) -> dict:
    size = 16 * scale
    return {"dataset": "data/tiny", "split": "test", "scale": scale, "frame_limit": None, "device": "cpu",
            "threads": 2, "torch_version": "x", "warmup_frames_per_sequence": 2,
            "sequences": [{"name": "a", "frames": 4, "input_resolution": "16x16",
                           "output_resolution": f"{size}x{size}", "camera_cuts": 0}],
            "timing_reference": {"label": "oidn:high", "ms_per_frame": reference_ms, "timing": {}},
            "fvvdp": {"enabled": False, "available": False, "reason": None, "failures": []},
            "methods": entries}


@pytest.fixture
def reports() -> list[dict]:
    x1 = report(1, [
        entry("identity", "identity", "default", 1, 0, 0.0, 17.0, 0.18, 0.01, 0.000125),
        entry("accumulation", "accumulation", "default", 1, 0, 0.0, 22.0, 0.17, 6.0, 0.075),
        entry("oidn:high", "oidn", "high", 1, 0, 0.0, 32.0, 0.09, 80.0, 1.0),
        entry("oidn:fast", "oidn", "fast", 1, 0, 0.0, 31.0, 0.10, 20.0, 0.25),
        entry("wskpn:s", "wskpn", "s", 1, 13000, 25900.0, 29.0, 0.14, 13.0, 0.16, "runs/a/best.pt"),
        entry("wskpn:s", "wskpn", "s", 1, 13000, 25900.0, 28.0, 0.15, 14.0, 0.175, "runs/b/best.pt"),
    ])
    x2 = report(2, [
        entry("identity", "identity", "default", 2, 0, 0.0, 16.0, 0.20, 0.02, 0.0002),
        entry("oidn:high", "oidn", "high", 2, 0, 0.0, 29.0, 0.12, 100.0, 1.0),
        entry("munet:s", "munet", "s", 2, 50000, 40000.0, 28.0, 0.11, 30.0, 0.3, "models:/munet-s-x2/3"),
        entry("svgf", "svgf", "default", 2, 0, 90.0, None, None, None, None),  # nothing measured
    ], reference_ms=100.0)
    return [x1, x2]


def test_rows_carry_the_table_fields(reports):
    rows = rows_from_report(reports[0])
    assert [r["label"] for r in rows][:3] == ["identity", "accumulation", "oidn:high"]
    row = rows[4]
    assert row["scale"] == 1 and row["params"] == 13000 and row["flops_per_pixel"] == 25900.0
    assert (row["psnr"], row["flip"], row["ssim"], row["temporal_error"]) == (29.0, 0.14, 0.5, 0.02)
    assert row["fvvdp_jod"] is None and row["ms_per_frame"] == 13.0 and row["time_ratio_to_oidn"] == 0.16
    assert row["input_resolution"] == "16x16" and row["output_resolution"] == "16x16" and row["threads"] == 2
    oidn = rows[2]
    assert oidn["cost_counted"] is False and oidn["params"] is None and oidn["flops_per_pixel"] is None
    assert rows[0]["cost_counted"] is True and rows[0]["params"] == 0


def test_benchmark_rows_sort_disambiguate_and_mark_fronts(reports):
    rows = benchmark_rows(reports)
    assert [(r["scale"], r["label"]) for r in rows] == [
        (1, "identity"), (1, "accumulation"), (1, "wskpn:s (a/best.pt)"), (1, "wskpn:s (b/best.pt)"),
        (1, "oidn:fast"), (1, "oidn:high"),
        (2, "identity"), (2, "munet:s"), (2, "oidn:high"), (2, "svgf")]
    front = {(r["scale"], r["label"]): r["pareto"] for r in rows}
    assert front[1, "identity"] == ["psnr", "flip"] and front[1, "oidn:high"] == ["psnr", "flip"]
    assert front[1, "wskpn:s (b/best.pt)"] == []  # slower and worse than the other checkpoint
    assert front[1, "wskpn:s (a/best.pt)"] == ["psnr", "flip"]
    # At 2x MUNet is faster than OIDN-high with a better FLIP but a worse PSNR: on both fronts; OIDN on PSNR's.
    assert front[2, "munet:s"] == ["psnr", "flip"] and front[2, "oidn:high"] == ["psnr"]
    assert front[2, "svgf"] == []


def test_table_has_one_row_per_method_preset_and_scale(reports):
    rows = benchmark_rows(reports)
    skipped = [{"method": "runs/jnds/best.pt", "scale": 1, "reason": "trained at scale 2"}]
    table = format_benchmark_table(rows, reports, skipped)
    lines = table.splitlines()
    header = next(line for line in lines if line.startswith("| method"))
    assert header == ("| method | scale | params | FLOPs/px | PSNR dB ↑ | FLIP ↓ | SSIM ↑ | temporal ↓ | JOD ↑ | "
                      "ms/frame | time / OIDN-high | front |")
    body = [line for line in lines if line.startswith("| ") and line != header]
    assert len(body) == len(rows) == 10
    wskpn = "| wskpn:s (a/best.pt) | x1 | 13k | 25.9k | 29.00 | 0.1400 | 0.5000 | 0.02000 | - | 13 | 0.16x |"
    assert f"{wskpn} PSNR, FLIP |" in body
    assert "| oidn:high | x1 | - | - | 32.00 |" in table  # OIDN's network is not counted by torch
    assert "| svgf | x2 | 0 | 90 | - | - | 0.5000 | 0.02000 | - | - | - |  |" in body
    assert any(line.startswith("- x1: 1 sequences, 4 frames, input 16x16 -> output 16x16") and "oidn:high 80 ms"
               in line for line in lines)
    assert any(line.startswith("- x2:") and "output 32x32" in line for line in lines)
    assert "- runs/jnds/best.pt at x1: trained at scale 2" in lines


def test_labels_of_the_same_preset_stay_apart():
    twins = [entry("afn:m", "afn", "m", 1, 9, 9.0, 20.0, 0.1, 1.0, 0.1, f"{run}/best.pt") for run in ("x/a", "y/a")]
    assert [r["label"] for r in benchmark_rows([report(1, twins)])] == ["afn:m #1", "afn:m #2"]


def test_document_keeps_every_report_and_is_json(reports):
    document = benchmark_document(reports, [])
    assert document["scales"] == [1, 2] and set(document["reports"]) == {"1", "2"}
    assert len(document["rows"]) == 10 and document["dataset"] == "data/tiny"
    json.dumps(document, allow_nan=False)
    with pytest.raises(ValueError, match="no evaluation reports"):
        benchmark_document([])


# --------------------------------------------------------------------------------------------- charts

def _texts(axis) -> set[str]:
    return {text.get_text() for text in axis.texts}


def _marker_paths(axis) -> dict[tuple[float, float], tuple]:
    """Each drawn point (x, y) -> its marker path's vertices (a hashable form)."""
    paths = {}
    for collection in axis.collections:
        offsets = collection.get_offsets()
        if len(offsets) and collection.get_paths():
            vertices = tuple(map(tuple, collection.get_paths()[0].vertices.round(3)))
            for x, y in offsets:
                paths[float(x), float(y)] = vertices
    return paths


def test_quality_speed_chart_labels_every_point_and_draws_the_fronts(reports):
    rows = benchmark_rows(reports)
    figure = quality_speed_figure(rows, title="tiny / test")
    psnr_axis, flip_axis = figure.axes
    drawn = {r["label"] for r in rows if r["ms_per_frame"] is not None}
    assert drawn == {"identity", "accumulation", "wskpn:s (a/best.pt)", "wskpn:s (b/best.pt)", "oidn:fast",
                     "oidn:high", "munet:s"}
    for axis in (psnr_axis, flip_axis):
        assert axis.get_xscale() == "log"
        assert drawn <= _texts(axis) and "svgf" not in _texts(axis)  # nothing to place it by
        labels = [t.get_text() for t in axis.texts]
        assert labels.count("identity") == 2 and labels.count("oidn:high") == 2  # once per scale
        legend = {t.get_text() for t in axis.get_legend().get_texts()}
        assert {"Pareto front x1", "Pareto front x2"} <= legend
        assert any(t.startswith("x1 ") for t in legend) and any(t.startswith("x2 ") for t in legend)
        # x1 and x2 points have different markers; all points of one scale share theirs.
        markers = _marker_paths(axis)
        key = "psnr" if axis is psnr_axis else "flip"
        x1 = {markers[r["ms_per_frame"], r[key]] for r in rows if r["scale"] == 1}
        x2 = {markers[r["ms_per_frame"], r[key]] for r in rows if r["scale"] == 2 and r["ms_per_frame"]}
        assert len(x1) == 1 and len(x2) == 1 and x1 != x2
    assert "PSNR" in psnr_axis.get_ylabel() and "FLIP" in flip_axis.get_ylabel()
    assert "log scale" in psnr_axis.get_xlabel() and "2 threads" in psnr_axis.get_xlabel()
    # The PSNR front at 1x: identity, accumulation, wskpn a, oidn:fast, oidn:high, in time order.
    front_x1 = next(line for line in psnr_axis.lines if line.get_label() == "Pareto front x1")
    assert list(front_x1.get_xdata()) == [0.01, 6.0, 13.0, 20.0, 80.0]
    assert list(front_x1.get_ydata()) == [17.0, 22.0, 29.0, 31.0, 32.0]
    front_x2 = next(line for line in flip_axis.lines if line.get_label() == "Pareto front x2")
    assert list(front_x2.get_xdata()) == [0.02, 30.0]  # OIDN-high is slower and worse on FLIP than MUNet


def test_quality_cost_chart_plots_against_params_and_flops(reports):
    rows = benchmark_rows(reports)
    figure = quality_cost_figure(rows)
    assert len(figure.axes) == 4
    labels = {r["label"] for r in rows if r["psnr"] is not None and not r["label"].startswith("oidn")}
    for axis in figure.axes:
        # OIDN's network runs outside torch: its cost is not counted, so it is not placed at 0 but named below.
        assert axis.get_xscale() == "symlog" and labels <= _texts(axis) and "oidn:high" not in _texts(axis)
    assert any("not shown: oidn:fast, oidn:high" in text.get_text() for text in figure.texts)
    assert [axis.get_xlabel().split()[0] for axis in figure.axes] == ["parameters", "FLOPs", "parameters", "FLOPs"]
    assert "quality against size and compute" in figure.get_suptitle()


def test_no_chart_without_measured_points():
    rows = benchmark_rows([report(1, [entry("svgf", "svgf", "default", 1, 0, 90.0, None, None, None, None)])])
    assert quality_speed_figure(rows) is None and quality_cost_figure(rows) is None


def test_write_benchmark_writes_tables_and_both_charts(reports, tmp_path):
    files = write_benchmark(tmp_path / "out", reports, [])
    assert set(files) == {"benchmark.json", "benchmark.md", QUALITY_SPEED_CHART, QUALITY_COST_CHART}
    for name in (QUALITY_SPEED_CHART, QUALITY_COST_CHART):
        assert files[name].read_bytes()[:8] == PNG_SIGNATURE and files[name].stat().st_size > 10_000
    assert json.loads(files["benchmark.json"].read_text())["rows"][0]["label"] == "identity"
    assert "| munet:s | x2 |" in files["benchmark.md"].read_text()


def _dense_cluster(frames_timed: int | None = None) -> list[dict]:
    """Two spread points and eighteen crowded together: three presets of fused, OIDN + TAA and OIDN at two scales
    (in the cost chart OIDN + TAA and fused all sit at 0 parameters, on one vertical line)."""
    entries = {1: [], 2: []}
    entries[1].append(entry("identity", "identity", "default", 1, 0, 0.0, 16.0, 0.20, 0.01, 0.0002))
    entries[2].append(entry("accumulation", "accumulation", "default", 2, 0, 0.0, 22.0, 0.17, 1.5, 0.03))
    for number, (method, preset) in enumerate([(m, p) for m in ("fused", "oidn-taa", "oidn")
                                               for p in ("fast", "balanced", "high")]):
        for scale in (1, 2):
            ms, psnr = 20.0 + 4 * number + scale, 31.0 + 0.15 * number - 0.4 * scale
            entries[scale].append(entry(f"{method}:{preset}", method, preset, scale, 0, 0.0, psnr,
                                        0.10 - 0.002 * number, ms, ms / 55.0))
    reports = [report(scale, items) for scale, items in entries.items()]
    for item in (e for r in reports for e in r["methods"]):
        item["timing"] = {"frames_timed": frames_timed}
    return benchmark_rows(reports)


@pytest.mark.parametrize("figure_of", [quality_speed_figure, quality_cost_figure])
def test_labels_of_a_dense_cluster_neither_overlap_nor_leave_the_plot(figure_of):
    rows = _dense_cluster()
    figure = figure_of(rows, title="dense")
    renderer = freeze_layout(figure)  # drawn again, as saving draws it
    for axis in figure.axes:
        # The text's own box (an Annotation's includes its leader line, which may cross other labels' space).
        boxes = [Text.get_window_extent(text, renderer) for text in axis.texts]
        assert len(boxes) >= 10
        frame = axis.get_window_extent(renderer)
        for index, box in enumerate(boxes):
            assert frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1, \
                axis.texts[index].get_text()
            for other in boxes[index + 1:]:
                assert not box.overlaps(other), (axis.texts[index].get_text(), box, other)
        legend = axis.get_legend()
        assert not any(box.overlaps(legend.get_window_extent(renderer)) for box in boxes)


def test_a_benchmark_timed_on_fewer_than_5_frames_says_so_in_table_and_chart():
    rows = _dense_cluster(frames_timed=2)
    note = "timed on fewer than 5 frames per method (2 at x1, 2 at x2)"
    assert note in format_benchmark_table(rows)
    assert note in quality_speed_figure(rows).get_suptitle()
    rows = _dense_cluster(frames_timed=5)
    assert "fewer than" not in format_benchmark_table(rows) + quality_speed_figure(rows).get_suptitle()
