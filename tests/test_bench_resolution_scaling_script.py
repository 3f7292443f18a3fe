"""scripts/bench_resolution_scaling.py: the fused suite's groups, and one tiny run's report (JSON, Markdown, chart)."""

from __future__ import annotations

import json

import pytest
import torch

from tests.builders import load_script

bench = load_script("bench_resolution_scaling")


def test_the_fused_suite_pairs_each_model_with_oidn_at_its_quality_and_4k_only_at_2x():
    groups = bench.fused_groups(["fused-fast-x1", "fused-balanced-x2"], ["512", "3840x2160"])
    assert groups == [("512", ["fused-fast-x1", "oidn:fast", "oidn-taa:fast"]),
                      ("512", ["fused-balanced-x2", "oidn:balanced@2", "oidn-taa:balanced@2"]),
                      ("3840x2160", ["fused-balanced-x2", "oidn:balanced@2", "oidn-taa:balanced@2"])]
    with pytest.raises(SystemExit, match="shipped fused models"):
        bench.fused_groups(["munet-s-x1"], [])
    assert bench.default_frames(128, 128) > bench.default_frames(512, 512) > bench.default_frames(1920, 1080)


def test_a_tiny_fused_run_writes_the_report_named_by_device(tmp_path, capsys):
    bench.main(["--suite", "fused", "--model", "fused-fast-x1", "--size", "24x16", "--frames", "2", "--warmup", "1",
                "--check-frames", "2", "--results", str(tmp_path)])
    (report_path,) = tmp_path.glob("speed_*_2-threads.json")
    report = json.loads(report_path.read_text())
    assert report["device"]["type"] == "cpu" and report["device"]["threads"] == 2
    assert len(report["load_average"]) == 2 and report["device"]["cores"] >= 1
    assert [row["model"] for row in report["rows"]] == ["fused-fast-x1", "oidn:fast", "oidn-taa:fast"]
    fused = report["rows"][0]
    assert fused["output"] == [24, 16] and fused["frames"] == 2
    assert fused["p95_ms"] >= fused["p50_ms"] > 0
    assert fused["ratio_to_oidn"] == pytest.approx(fused["p50_ms"] / report["rows"][1]["p50_ms"], rel=1e-3)
    assert 0 <= fused["learned_share"] <= 1 and fused["learned_p50_ms"] <= fused["p50_ms"]
    assert fused["check"]["frames"] == 3 and fused["check"]["max_abs_diff"] >= 0
    assert report_path.with_suffix(".md").read_text().count("| fused-fast-x1 | 24x16 |") == 1
    assert report_path.with_suffix(".png").stat().st_size > 0
    assert "report:" in capsys.readouterr().out


@pytest.mark.skipif(torch.cuda.is_available(), reason="the refusal shows only where the device is missing")
def test_cuda_without_a_cuda_device_is_refused_with_a_message():
    with pytest.raises(SystemExit, match="no CUDA device"):
        bench.main(["--suite", "fused", "--device", "cuda", "--size", "32"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_cuda_the_fused_step_replays_graphs_that_match_the_eager_model(tmp_path):
    bench.main(["--suite", "fused", "--model", "fused-balanced-x2", "--size", "128x96", "--frames", "4",
                "--device", "cuda", "--results", str(tmp_path)])
    (report_path,) = tmp_path.glob("speed_*.json")
    fused = json.loads(report_path.read_text())["rows"][0]
    assert fused["form"] == "cuda-graph" and fused["cuda_graph_captures"] >= 1
    assert fused["oidn_device"] in ("cuda", "cpu") and fused["check"]["frames"] == 6  # 3 warm-up, 3 replays
    assert fused["check"]["min_psnr_db"] > 80  # the replays compute what the eager model computes


def _report(size: int, command: str, load: list[float]) -> dict:
    rows = [{"model": "fused-fast-x1", "method": "fused", "learned": True, "scale": 1, "output": [size, size],
             "render": [size, size], "form": "eager", "frames": 2, "p50_ms": 3.0, "p95_ms": 4.0, "peak_mb": 1.0,
             "step_mb": 0.0, "ratio_to_oidn": 3.0, "learned_p50_ms": 2.0, "learned_share": 0.66},
            {"model": "oidn:fast", "method": "oidn", "learned": False, "scale": 1, "output": [size, size],
             "render": [size, size], "frames": 2, "p50_ms": 1.0, "p95_ms": 1.5, "peak_mb": 1.0, "step_mb": 0.0}]
    return {"device": {"type": "cpu", "name": "Test CPU 9000", "threads": 2, "cores": 2}, "torch": "x", "warmup": 2,
            "load_average": load, "commands": [command], "rows": rows}


def test_a_merged_report_keeps_the_other_rows_and_every_run_s_command(tmp_path):
    bench.write_results(_report(128, "run a", [0.5, 0.7]), tmp_path, merge=True)
    path = bench.write_results(_report(512, "run b", [0.2, 0.3]), tmp_path, merge=True)
    assert path.name == "speed_test-9000_2-threads.json"
    report = json.loads(path.read_text())
    assert [row["output"][0] for row in report["rows"]] == [128, 128, 512, 512]
    assert report["commands"] == ["run a", "run b"] and report["load_average"] == [0.5, 0.7, 0.2, 0.3]
    page = path.with_suffix(".md").read_text()
    assert "load average 0.5 -> 0.7, 0.2 -> 0.3" in page and "Regenerate (in order): `run a`<br>`run b`" in page
    assert "![ratio to OIDN](speed_test-9000_2-threads.png)" in page
