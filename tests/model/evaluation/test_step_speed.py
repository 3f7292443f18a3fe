"""model.evaluation.step_speed: percentiles, the learned part, the output check and the interleaved group timing,
on fake timings with known answers (a virtual clock that only the fake steps and the fake OIDN advance)."""

from __future__ import annotations

import pytest
import torch

import model.methods.oidn as oidn
from model.evaluation.step_speed import (compare_outputs, file_stem, learned_part, markdown_table, merge_rows,
                                         percentile, rounded, speed_rows, summary_ms, time_group)
from model.methods.registry import example_batch


def test_percentiles_interpolate_between_ranks():
    assert percentile([4.0, 1.0, 3.0, 2.0], 50) == pytest.approx(2.5)
    assert percentile([1.0, 2.0, 3.0, 4.0], 95) == pytest.approx(3.85)
    assert percentile([7.0], 95) == 7.0
    with pytest.raises(ValueError):
        percentile([], 50)
    assert summary_ms([0.010, 0.030, 0.020]) == pytest.approx({"p50_ms": 20.0, "p95_ms": 29.0, "frames": 3})


def test_the_learned_part_is_the_step_less_its_oidn_call():
    part = learned_part([0.10, 0.12, 0.20], [0.04, 0.05, 0.05])
    assert part["oidn_in_step_p50_ms"] == pytest.approx(50.0)
    assert part["learned_p50_ms"] == pytest.approx(70.0)  # learned: 60, 70, 150 ms
    assert part["learned_share"] == pytest.approx(0.6)  # shares 0.6, 0.583, 0.75
    with pytest.raises(ValueError):
        learned_part([0.1], [])


def test_the_output_check_names_the_largest_difference_and_the_lowest_psnr():
    image = torch.rand(1, 3, 4, 4)
    same = compare_outputs([image, image], [image.clone(), image.clone()])
    assert same == {"frames": 2, "max_abs_diff": 0.0, "min_psnr_db": 200.0}
    off = image.clone()
    off[0, 0, 1, 2] += 0.25
    check = compare_outputs([image, off], [image, image])
    assert check["max_abs_diff"] == pytest.approx(0.25)
    assert check["min_psnr_db"] < 60.0


class VirtualClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self, call, device):
        start = self.now
        return call(), self.now - start


class FakeMethod:
    """A step that costs ``cost`` virtual seconds besides ``oidn_calls`` OIDN calls; logs its calls."""

    def __init__(self, clock, log, name, cost, oidn_calls=1, offset=0.0):
        self.clock, self.log, self.name, self.cost, self.oidn_calls, self.offset = clock, log, name, cost, \
            oidn_calls, offset

    def step(self, frame, state):
        self.log.append(self.name)
        self.clock.now += self.cost
        output = frame.color
        for _ in range(self.oidn_calls):
            output = oidn.oidn_denoise(frame, "fast")
        return output + self.offset, {"count": (state or {"count": 0})["count"] + 1}


@pytest.fixture
def clock(monkeypatch):
    clock = VirtualClock()

    def fake_denoise(frame, quality):
        clock.now += 0.03
        return frame.color

    monkeypatch.setattr(oidn, "_denoise", fake_denoise)
    return clock


def test_a_group_is_timed_interleaved_with_ratios_learned_part_and_check(clock):
    log: list[str] = []
    methods = {"fused-x": FakeMethod(clock, log, "fused-x", 0.07), "oidn:fast": FakeMethod(clock, log, "oidn", 0.0),
               "oidn-taa:fast": FakeMethod(clock, log, "oidn-taa", 0.01)}
    references = {"fused-x": FakeMethod(clock, [], "reference", 0.5, offset=0.125)}
    frames = [example_batch(8, 8, seed=seed) for seed in range(5)]
    records = time_group(methods, frames, "cpu", warmup=2, references=references, check_frames=2, clock=clock)
    assert log[:6] == ["fused-x", "oidn", "oidn-taa", "oidn", "oidn-taa", "fused-x"]  # each frame in a rotated order
    assert records["fused-x"].seconds == pytest.approx([0.10] * 3)
    assert records["fused-x"].oidn_seconds == pytest.approx([0.03] * 3)
    assert records["fused-x"].reference_seconds == pytest.approx([0.53] * 2)
    assert records["fused-x"].check["frames"] == 4  # the warm-up frames and the first two timed ones
    assert records["fused-x"].check["max_abs_diff"] == pytest.approx(0.125)
    assert records["oidn:fast"].check is None

    group = [{"label": "fused-x", "method": "fused", "learned": True, "scale": 1, "output": [8, 8],
              "render": [8, 8], "form": "eager"},
             {"label": "oidn:fast", "method": "oidn", "learned": False, "scale": 1, "output": [8, 8],
              "render": [8, 8]},
             {"label": "oidn-taa:fast", "method": "oidn-taa", "learned": False, "scale": 1, "output": [8, 8],
              "render": [8, 8]}]
    rows = speed_rows(group, records)
    fused = rows[0]
    assert fused["model"] == "fused-x" and fused["frames"] == 3
    assert fused["p50_ms"] == pytest.approx(100.0) and fused["p95_ms"] == pytest.approx(100.0)
    assert fused["ratio_to_oidn"] == pytest.approx(0.10 / 0.03)
    assert fused["ratio_to_oidn_taa"] == pytest.approx(0.10 / 0.04)
    assert fused["learned_p50_ms"] == pytest.approx(70.0) and fused["learned_share"] == pytest.approx(0.7)
    assert fused["eager_p50_ms"] == pytest.approx(530.0)
    assert "ratio_to_oidn" not in rows[1] and "learned_share" not in rows[1]
    report = {"device": {"type": "cpu", "name": "Test CPU", "threads": 2}, "torch": "x", "warmup": 2, "rows": rows}
    table = markdown_table(report)
    assert "| fused-x | 8x8 | 8x8 | eager | 3 | 100.0 | 100.0 |" in table
    assert "| 3.33 | 2.50 | 530.0 | 1.25e-01 |" in table
    rows[0].update(form="cuda-graph", cuda_graph_captures=2)
    assert "| fused-x | 8x8 | 8x8 | cuda-graph (2 captured) | 3 |" in markdown_table(report)


def test_a_quick_run_replaces_only_the_rows_it_measured_again():
    old = [{"model": "a", "output": [8, 8], "p50_ms": 1.0}, {"model": "a", "output": [16, 16], "p50_ms": 2.0}]
    new = [{"model": "a", "output": [16, 16], "p50_ms": 3.0}, {"model": "b", "output": [8, 8], "p50_ms": 4.0}]
    assert [row["p50_ms"] for row in merge_rows(old, new)] == [1.0, 3.0, 4.0]


def test_result_files_are_named_by_the_device():
    assert file_stem("Intel(R) Xeon(R) Platinum 8488C CPU @ 2.40GHz", "cpu", 2) == \
        "speed_intel-xeon-platinum-8488c_2-threads"
    assert file_stem("NVIDIA H100 80GB HBM3", "cuda", 8) == "speed_nvidia-h100-80gb-hbm3"


def test_report_floats_are_rounded_to_significant_digits():
    assert rounded({"rows": [{"ms": 123.456789, "frames": 6, "check": {"psnr": 0.000123456}}]}) == \
        {"rows": [{"ms": 123.5, "frames": 6, "check": {"psnr": 0.0001235}}]}


def test_the_reference_step_runs_on_torch_ops_and_the_timed_one_on_the_native_kernels():
    from model.ops import native

    seen = []

    class Recorder:
        def step(self, frame, state):
            seen.append(native.enabled())
            return torch.zeros(1, 3, 2, 2), state

    frames = [object(), object()]
    time_group({"model": Recorder()}, frames, "cpu", warmup=0, references={"model": Recorder()},
               check_frames=2)
    assert seen == [True, False, True, False] and native.enabled()
