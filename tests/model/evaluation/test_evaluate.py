"""The evaluation protocol on a tiny synthetic dataset: report shape, plumbing of metrics, history, cuts, timing."""

from __future__ import annotations

import json
import math
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from model.io.dataset import Dataset, DatasetError
from model.evaluation.evaluate import (EvaluationSequence, _checked_output, evaluate, evaluate_method, format_table,
                                      run_sequence)
from model.methods.base import FrameBatch, State
from model.evaluation.metrics import frame_metrics
from tests.builders import GRADIENT_FRAMES as FRAMES
from tests.builders import NoisyInput, write_gradient_dataset


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory) -> Path:
    return write_gradient_dataset(tmp_path_factory.mktemp("eval") / "data")


class NaNOutput(NoisyInput):
    name = "nan_output"

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        return torch.full_like(frame.color, math.nan), {}


def run(dataset_dir: Path, methods, **options) -> dict:
    options.setdefault("vdp", False)
    options.setdefault("timing_reference", None)
    return evaluate(dataset_dir, methods, **options)


def test_report_has_every_metric_and_timing_finite_and_json_ready(dataset_dir):
    reference = NoisyInput()  # stands in for OIDN: any method can be the timing reference
    report = run(dataset_dir, [NoisyInput()], timing_reference=reference)
    json.dumps(report, allow_nan=False)  # strict JSON: no NaN or Infinity anywhere
    assert report["split"] == "test" and report["scale"] == 1
    assert [s["name"] for s in report["sequences"]] == ["a", "b"]
    assert report["sequences"][1]["camera_cuts"] == 1
    (entry,) = report["methods"]
    assert entry["label"] == "noisy_input" and entry["params"] == 0 and entry["flops_per_pixel"] == 0
    assert set(entry["sequences"]) == {"a", "b"}
    for name in ("psnr", "ssim", "flip", "smape", "temporal_error"):
        assert math.isfinite(entry["metrics"][name]), name
    assert entry["metrics"]["fvvdp_jod"] is None and report["fvvdp"]["enabled"] is False
    timing = entry["timing"]
    assert timing["frames_timed"] == 2 * (FRAMES - 2)  # the first 2 frames of each sequence are warm-up
    assert timing["input_resolutions"] == ["16x16"] and timing["output_resolutions"] == ["16x16"]
    assert timing["threads"] == torch.get_num_threads()
    assert entry["ms_per_frame"] > 0 and entry["time_ratio_to_oidn"] > 0
    assert report["timing_reference"]["label"] == "noisy_input"
    assert report["timing_reference"]["timing"]["frames_timed"] == 2 * (FRAMES - 2)


def test_metrics_are_per_frame_means_averaged_over_sequences(dataset_dir):
    report = run(dataset_dir, [NoisyInput()])
    expected = {}
    for name in ("a", "b"):
        sequence = EvaluationSequence.from_sequence(Dataset(dataset_dir).sequence(name), scale=1)
        values = [frame_metrics(f.color, f.reference) for f in sequence.frames]
        expected[name] = {k: float(np.mean([v[k][0] for v in values])) for k in ("psnr", "ssim", "flip", "smape")}
    entry = report["methods"][0]
    for metric in ("psnr", "ssim", "flip", "smape"):
        for name in ("a", "b"):
            assert entry["sequences"][name][metric] == pytest.approx(expected[name][metric], rel=1e-5)
        mean = (expected["a"][metric] + expected["b"][metric]) / 2
        assert entry["metrics"][metric] == pytest.approx(mean, rel=1e-5)
    assert 5 < entry["metrics"]["psnr"] < 30  # noise of sigma 0.2: clearly imperfect, clearly not garbage


def test_sequences_are_reported_by_their_dataset_names_when_their_own_names_repeat(dataset_dir, tmp_path):
    # A dataset of links to other datasets' sequences (one scene at two resolutions, say) can hold two whose own
    # manifests name them alike: each gets its own row, under the name the dataset gives it.
    mixed = Dataset.create(tmp_path / "mixed")
    for link in ("a_128", "a_256"):
        (tmp_path / "mixed" / link).symlink_to(dataset_dir / "a")
        mixed.add_sequence_dir(link, "test")
    report = run(tmp_path / "mixed", [NoisyInput()])
    assert [s["name"] for s in report["sequences"]] == ["a_128", "a_256"]
    assert set(report["methods"][0]["sequences"]) == {"a_128", "a_256"}


def test_history_is_carried_reset_per_sequence_and_at_cuts_and_reference_is_hidden(dataset_dir):
    method = NoisyInput()
    run(dataset_dir, [method])
    seen = method.seen[-2 * FRAMES:]  # the steps before these count FLOPs on an example batch
    histories = [s["history"] for s in seen]
    # Sequence a: fresh, then 1, 2, 3 frames of history; sequence b: fresh, 1, cut (fresh), 1.
    assert histories == [None, 1, 2, 3, None, 1, None, 1]
    assert [s["cut"] for s in seen] == [False] * 6 + [True, False]
    assert not any(s["reference"] for s in seen)


def test_scale_two_compares_against_the_scale_two_reference(dataset_dir):
    report = run(dataset_dir, [NoisyInput(scale=2)], scale=2)
    assert report["sequences"][0]["output_resolution"] == "32x32"
    assert report["methods"][0]["timing"]["output_resolutions"] == ["32x32"]
    assert math.isfinite(report["methods"][0]["metrics"]["psnr"])
    with pytest.raises(ValueError, match="scale 1"):
        run(dataset_dir, [NoisyInput(scale=1)], scale=2)


def test_frame_limit_and_a_timing_reference_that_is_also_evaluated(dataset_dir):
    report = run(dataset_dir, [NoisyInput()], frame_limit=3, timing_reference="noisy_input")
    entry = report["methods"][0]
    assert [s["frames"] for s in report["sequences"]] == [3, 3]
    assert entry["timing"]["frames_timed"] == 2
    assert entry["time_ratio_to_oidn"] == 1.0  # its own run is the reference timing, not a second one


def test_fovvideovdp_jod_per_sequence(dataset_dir):
    report = run(dataset_dir, [NoisyInput()], vdp=True, frame_limit=2)
    assert report["fvvdp"] == {"enabled": True, "available": True, "reason": None, "display": "standard_4k",
                               "frames_per_second": 30, "failures": []}
    jods = [report["methods"][0]["sequences"][name]["fvvdp_jod"] for name in ("a", "b")]
    assert all(0 < jod < 10 for jod in jods)


def test_evaluate_method_on_sequences_in_memory(dataset_dir):
    sequences = [EvaluationSequence.from_sequence(s, 1, 2) for s in Dataset(dataset_dir).sequences("test")]
    entry = evaluate_method(NoisyInput(), sequences, vdp=False, reference_ms=1e6)
    assert entry["timing"]["frames_timed"] == 0 and entry["ms_per_frame"] is None
    assert entry["time_ratio_to_oidn"] is None and math.isfinite(entry["metrics"]["ssim"])


def test_run_sequence_keeps_the_outputs_and_says_whether_the_method_keeps_history(dataset_dir):
    sequence = EvaluationSequence.from_sequence(Dataset(dataset_dir).sequence("a"), 2)
    run = run_sequence(NoisyInput(scale=2), sequence, keep_outputs=True)
    expected = torch.cat([f.color.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3) for f in sequence.frames])
    assert torch.equal(run["outputs"], expected) and run["keeps_history"]  # its state holds a count
    per_frame = run_sequence(NaNOutput(), EvaluationSequence.from_sequence(Dataset(dataset_dir).sequence("a"), 1),
                             with_metrics=False)
    assert not per_frame["keeps_history"] and "outputs" not in per_frame  # it returns an empty state
    with pytest.raises(ValueError, match="keep_outputs needs with_metrics"):
        run_sequence(NoisyInput(), sequence, with_metrics=False, keep_outputs=True)


def test_an_existing_file_is_loaded_as_a_checkpoint(dataset_dir, tmp_path, monkeypatch):
    loaded = []

    def load_method(path, scale=None):
        loaded.append((Path(path), scale))
        return NoisyInput(scale=scale)

    # Stands in for model.training.checkpoint (its own tests cover the file format): only the routing is tested here.
    monkeypatch.setitem(sys.modules, "model.training.checkpoint", types.SimpleNamespace(load_method=load_method))
    checkpoint = tmp_path / "trained.pt"
    checkpoint.write_bytes(b"weights")
    report = run(dataset_dir, [str(checkpoint)], frame_limit=1)
    assert loaded == [(checkpoint, 1)]
    assert report["methods"][0]["source"] == str(checkpoint) and report["methods"][0]["label"] == "noisy_input"
    # The evaluated scale is passed on: load_method decides whether the checkpoint can run at it.
    run(dataset_dir, [str(checkpoint)], scale=2, frame_limit=1)
    assert loaded[-1] == (checkpoint, 2)


def test_a_method_computing_nan_returns_black_frames_through_the_output_bound(dataset_dir):
    report = run(dataset_dir, [NaNOutput()])
    row = report["methods"][0]
    assert math.isfinite(row["metrics"]["psnr"]) and row["metrics"]["psnr"] > 0


def test_non_finite_output_is_an_error_naming_method_sequence_and_frame(dataset_dir):
    # No Method's step returns one (the output bound); the evaluator still checks what it is handed.
    sequence = EvaluationSequence.from_sequence(Dataset(dataset_dir).sequence("a"), scale=1)
    nan = torch.full_like(sequence.frames[0].reference, math.nan)
    with pytest.raises(RuntimeError, match="nan_output on sequence 'a', frame 0: output is not finite"):
        _checked_output(nan, sequence.frames[0], NaNOutput(), sequence, 0)


def test_bad_input_is_reported_before_any_frame_is_read(tmp_path, dataset_dir):
    with pytest.raises(DatasetError, match="not found"):
        run(tmp_path / "missing", [NoisyInput()])
    with pytest.raises(ValueError, match=r"no sequences in split 'validation' \(splits present: test \(2\)\)"):
        run(dataset_dir, [NoisyInput()], split="validation")
    only_scale_one = write_gradient_dataset(tmp_path / "scale1", scales=(1,))
    with pytest.raises(ValueError, match="sequence 'a' .* has no references at scale 2 .*1 more"):
        run(only_scale_one, [NoisyInput(scale=2)], scale=2)
    with pytest.raises(KeyError, match="unknown method 'no_such_method'"):
        run(dataset_dir, ["no_such_method"])
    with pytest.raises(FileNotFoundError, match="checkpoint runs/missing.pt not found"):
        run(dataset_dir, ["runs/missing.pt"])
    with pytest.raises(KeyError, match="cannot build the timing reference 'nope'"):
        run(dataset_dir, [NoisyInput()], timing_reference="nope")


def test_markdown_table_has_a_row_per_method_and_states_the_conditions(dataset_dir):
    report = run(dataset_dir, [NoisyInput(), NoisyInput()], timing_reference=NoisyInput())
    table = format_table(report)
    lines = table.splitlines()
    assert "2 sequences, 8 frames" in lines[0] and "input 16x16 -> output 16x16" in lines[0]
    assert f"{torch.get_num_threads()} threads" in lines[0] and "FovVideoVDP skipped" in lines[0]
    header = [cell.strip() for cell in lines[2].strip("|").split("|")]
    assert header[:4] == ["method", "params", "FLOPs/px", "PSNR dB ↑"] and header[-1] == "time / OIDN"
    rows = [line for line in lines[4:] if line.startswith("| noisy_input")]
    assert len(rows) == 2
    cells = [cell.strip() for cell in rows[0].strip("|").split("|")]
    assert cells[3] == f"{report['methods'][0]['metrics']['psnr']:.2f}" and cells[-1].endswith("x")


def test_rows_of_one_method_from_several_sources_name_their_source(dataset_dir):
    report = run(dataset_dir, [NoisyInput()], timing_reference=NoisyInput())
    first = report["methods"][0]
    report["methods"] = [{**first, "source": "pretrained-x1"}, {**first, "source": "models:/mine@champion"},
                         {**first, "source": "noisy_input"}]
    names = [line.split("|")[1].strip() for line in format_table(report).splitlines()[4:]]
    assert names == ["noisy_input (pretrained-x1)", "noisy_input (models:/mine@champion)", "noisy_input"]


def test_the_table_says_not_counted_for_a_network_torch_does_not_run(dataset_dir):
    report = run(dataset_dir, [NoisyInput()], timing_reference=NoisyInput())
    report["methods"].append({**report["methods"][0], "label": "oidn:high", "method": "oidn"})
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")]
            for line in format_table(report).splitlines()[4:]}
    assert rows["oidn:high"][1:3] == ["-", "-"]  # OIDN's own library: torch counts neither, so not "0"
    assert rows["noisy_input"][1:3] == ["0", "0"]
