"""The stability suite on tiny synthetic sequences: scenario construction, corruptions, scoring, report files."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from model.io.dataset import Dataset, SequenceWriter
from model.evaluation.evaluate import EvaluationSequence
from model.io.frames import FrameBundle
from model.evaluation.metrics import PSNR_CAP_DB
from model.methods.base import FrameBatch, Method, State
from model.methods.registry import build_method
from model.evaluation.stability import (DERIVED_SCENARIOS, EXPOSURE_BRIGHT, MIN_DROP_DB, SCENE_SCENARIOS, Scenario,
                             build_scenarios, derive_scenarios, fails_worst, name_shared_labels, run_suite,
                             scale_exposure)
from model.evaluation.stability_report import write_report
from model.ops.output_bound import OUTPUT_BOUND_FACTOR
from cli.main import main
from tests.builders import GRADIENT_FRAMES as FRAMES
from tests.builders import GRADIENT_SIZE as SIZE
from tests.builders import gradient_frame

CHEAP_METHODS = ("identity", "accumulation", "svgf")


def full_frame(index: int, seed: int, camera_cut: bool = False):
    """The evaluation tests' synthetic frame with every optional buffer (diffuse + specular == color)."""
    frame = gradient_frame(index, seed, (1, 2), camera_cut=camera_cut)
    diffuse = (frame.color * 0.75).astype(np.float32)
    return dataclasses.replace(frame, diffuse=diffuse, specular=(frame.color - diffuse).astype(np.float32),
                               specular_albedo=np.full((SIZE, SIZE, 3), 0.04, np.float32),
                               roughness=np.full((SIZE, SIZE), 0.5, np.float32))


def write_scene_dataset(root: Path) -> Path:
    """Three 4-frame 16x16 sequences named after generator scenes: a clean base, a moving object, a cut."""
    dataset = Dataset.create(root)
    for seed, (name, scene, split) in enumerate((("room", "diffuse_room", "train"), ("mover", "moving_object", "test"),
                                                 ("cut", "camera_cut", "test"))):
        with SequenceWriter(root / name, name, scene=scene) as writer:
            for index in range(FRAMES):
                writer.add(full_frame(index, seed, camera_cut=(scene == "camera_cut" and index == 2)))
        dataset.add_sequence_dir(name, split)
    return root


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return write_scene_dataset(tmp_path_factory.mktemp("stability") / "data")


@pytest.fixture(scope="module")
def clean(data_dir) -> EvaluationSequence:
    return EvaluationSequence.from_sequence(Dataset(data_dir).sequence("room"), scale=1)


class NeedsSpecular(Method):
    """Uses the specular buffer without checking it is there: fails when optional buffers are missing."""

    name = "needs_specular"

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        return frame.color + 0.0 * frame.specular, {}


class NaNOnFastMotion(Method):
    """Computes NaN when motion is larger than the image: the output bound must keep it from leaving the step."""

    name = "nan_on_fast_motion"

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        if float(frame.motion.abs().max()) > 2:
            return torch.full_like(frame.color, math.nan), {}
        return frame.color, {}


class BlendWithPrevious(Method):
    """Trusts its history blindly: output = w * previous output + (1 - w) * color (nearest-upscaled to the
    output scale), w = the preset. It ghosts."""

    name = "blend"

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        weight = float(self.preset)
        color = frame.color.repeat_interleave(self.scale, dim=2).repeat_interleave(self.scale, dim=3)
        output = color if state is None else weight * state["previous"] + (1 - weight) * color
        return output, {"previous": output}


def finite(tensor: torch.Tensor) -> bool:
    return bool(torch.isfinite(tensor).all())


# ------------------------------------------------------------------------------------------- scenarios

def test_exposure_scales_radiance_and_references_but_not_guides(clean):
    bright = scale_exposure(clean.frames, EXPOSURE_BRIGHT)
    for before, after in zip(clean.frames, bright):
        for name in ("color", "diffuse", "specular", "reference"):
            torch.testing.assert_close(getattr(after, name), 16.0 * getattr(before, name))
        for name in ("albedo", "specular_albedo", "normal", "depth", "motion", "roughness", "jitter"):
            assert getattr(after, name) is getattr(before, name)
    dark = {s.name: s for s in derive_scenarios(clean, ("exposure_dark",))}["exposure_dark"]
    torch.testing.assert_close(dark.frames[1].reference, clean.frames[1].reference / 16.0)


def test_derived_scenarios_corrupt_only_what_they_name(clean):
    before = [f.color.clone() for f in clean.frames]
    scenarios = {s.name: s for s in derive_scenarios(clean)}
    assert list(scenarios) == list(DERIVED_SCENARIOS)
    assert all(s.derived and s.source == "room" for s in scenarios.values())
    assert len(scenarios["first_frames"].frames) == 3 and len(scenarios["clean"].frames) == FRAMES
    corrupted = scenarios["nan_inf_color"].frames
    for name in ("color", "diffuse", "specular"):
        values = torch.stack([getattr(f, name) for f in corrupted])
        assert torch.isnan(values).any() and torch.isposinf(values).any() and torch.isneginf(values).any(), name
    assert all(finite(f.reference) and finite(f.albedo) and finite(f.motion) for f in corrupted)
    guides = scenarios["nan_inf_guides"].frames
    assert not finite(guides[0].depth) and not finite(guides[0].normal) and finite(guides[0].color)
    assert finite(guides[0].jitter) and not finite(guides[1].jitter)
    assert all(float(f.motion.abs().max()) == 0 for f in scenarios["zero_motion"].frames)
    garbage = torch.stack([f.motion for f in scenarios["garbage_motion"].frames])
    assert float(garbage.abs().max()) <= SIZE / 2 and float(garbage.abs().mean()) > 1.0
    missing = scenarios["missing_buffers"].frames[0]
    assert missing.diffuse is None and missing.specular is None and missing.roughness is None
    assert missing.specular_albedo is None and missing.color is clean.frames[0].color
    assert all(torch.equal(a, f.color) for a, f in zip(before, clean.frames))  # the clean frames are not modified
    # Ghost trails are measured with the motion that is true: the base's, not the corrupted one.
    for name in ("zero_motion", "garbage_motion", "nan_inf_guides", "first_frames"):
        assert all(m is f.motion for m, f in zip(scenarios[name].true_motion, clean.frames)), name
        assert len(scenarios[name].true_motion) == len(scenarios[name].frames)
    torch.testing.assert_close(scenarios["garbage_motion"].trails(), scenarios["clean"].trails())


def test_build_scenarios_matches_scenes_picks_the_base_and_reports_what_is_missing(data_dir):
    scenarios, missing = build_scenarios(data_dir, scale=1)
    names = [s.name for s in scenarios]
    assert names == ["moving_object", "camera_cut"] + list(DERIVED_SCENARIOS)
    by_name = {s.name: s for s in scenarios}
    assert by_name["moving_object"].source == "mover" and by_name["clean"].source == "room"
    assert by_name["camera_cut"].sequence.camera_cuts == [False, False, True, False]
    assert {m["name"] for m in missing} == {"moving_light", "fast_camera", "metals", "glass", "dark_fireflies",
                                            "visible_emitter", "orbiting_light", "sliding_over_texture"}
    assert all("no sequence of scene" in m["reason"] for m in missing)
    chosen, _ = build_scenarios(data_dir, names=("clean", "zero_motion"), base="cut", frame_limit=2)
    assert [s.source for s in chosen] == ["cut", "cut"] and len(chosen[0].frames) == 2
    with pytest.raises(ValueError, match="unknown scenario 'snow'"):
        build_scenarios(data_dir, names=("snow",))
    with pytest.raises(ValueError, match="no sequence 'nope'"):
        build_scenarios(data_dir, base="nope")
    _, no_scale = build_scenarios(data_dir, scale=4, names=("moving_object",))
    assert no_scale == [{"name": "moving_object", "reason": "sequence 'mover' has no references at scale 4"}]


# ------------------------------------------------------------------------------------------- fails worst

def test_fails_worst_names_the_largest_drop_in_gain_not_the_lowest_psnr():
    # dark_scene has the lowest PSNR, but the input is bad there too: gain 8 dB, as usual (median 8).
    # nan gains only 4 dB where the method usually gains 8: that is where it fails worst, by 4 dB.
    psnr = {"clean": 30.0, "dark_scene": 20.0, "nan": 24.0}
    inputs = {"clean": 20.0, "dark_scene": 12.0, "nan": 20.0}
    worst = fails_worst(psnr, inputs)
    assert worst["scenario"] == "nan" and not worst["failed"]
    assert worst["drop_db"] == pytest.approx(4.0) and worst["gain_db"] == pytest.approx(4.0)
    assert worst["median_gain_db"] == pytest.approx(8.0)
    assert worst["drops"] == pytest.approx({"clean": -2.0, "dark_scene": 0.0, "nan": 4.0})
    # A failure outranks any drop.
    failed = fails_worst({**psnr, "glass": None}, {**inputs, "glass": 15.0}, {"glass": "RuntimeError: NaN"})
    assert failed["scenario"] == "glass" and failed["failed"] and failed["reason"] == "RuntimeError: NaN"
    assert failed["median_gain_db"] == pytest.approx(8.0)  # failures are left out of the median
    # The same gain everywhere (the noisy input itself): no worst scenario.
    flat = fails_worst({"a": 20.0, "b": 25.0}, {"a": 20.0 - MIN_DROP_DB / 2, "b": 25.0})
    assert flat["scenario"] is None and flat["drop_db"] is None


# ------------------------------------------------------------------------------------------------ suite

@pytest.fixture(scope="module")
def suite(data_dir, tmp_path_factory):
    scenarios, missing = build_scenarios(data_dir, scale=1)
    methods = list(CHEAP_METHODS) + [NeedsSpecular(), NaNOnFastMotion()]
    # One torch thread: tiny frames gain nothing from more, and a busy machine makes extra threads spin.
    report = run_suite(scenarios, methods, scale=1, missing=missing, data=str(data_dir), threads=1)
    out = tmp_path_factory.mktemp("report")
    return report, write_report(report, out), out


def test_every_cheap_method_is_finite_in_every_scenario(suite):
    report, _, _ = suite
    entries = {e["label"]: e for e in report["methods"]}
    for label in CHEAP_METHODS:
        entry = entries[label]
        assert entry["failures"] == [], label
        for name, run in entry["scenarios"].items():
            assert run["status"] == "ok", (label, name)
            values = [run[k] for k in ("psnr", "ssim", "flip", "smape", "temporal_error")] + run["per_frame_psnr"]
            assert all(math.isfinite(v) for v in values), (label, name)
            assert len(run["per_frame_psnr"]) == (3 if name == "first_frames" else FRAMES)
    # The noisy input is the floor the gains are measured from: identity gains nothing anywhere.
    assert all(abs(run["gain_db"]) < 1e-4 for run in entries["identity"]["scenarios"].values())
    assert entries["identity"]["worst"]["scenario"] is None
    assert entries["accumulation"]["scenarios"]["clean"]["gain_db"] > 1.0  # it does denoise static frames


def test_failures_are_recorded_and_named_as_the_worst_scenario(suite):
    report, _, _ = suite
    entries = {e["label"]: e for e in report["methods"]}
    fragile = entries["needs_specular"]
    assert [f["scenario"] for f in fragile["failures"]] == ["missing_buffers"]
    assert fragile["worst"]["scenario"] == "missing_buffers" and fragile["worst"]["failed"]
    assert "TypeError" in fragile["worst"]["reason"] or "AttributeError" in fragile["worst"]["reason"]
    # Its NaN never leaves the step (model.ops.output_bound): it completes garbage_motion, with black frames.
    nan_method = entries["nan_on_fast_motion"]
    assert nan_method["failures"] == [] and nan_method["scenarios"]["garbage_motion"]["status"] == "ok"
    assert nan_method["scenarios"]["garbage_motion"]["output_ratio"] == 0.0
    assert nan_method["scenarios"]["clean"]["output_ratio"] == pytest.approx(1.0)  # it returns the input there


def test_the_report_states_each_methods_worst_output_to_input_ratio(suite):
    report, _, out = suite
    for entry in report["methods"]:
        ratios = [run["output_ratio"] for run in entry["scenarios"].values() if run["status"] == "ok"]
        assert ratios and all(0.0 <= r <= OUTPUT_BOUND_FACTOR + 1e-6 for r in ratios), entry["label"]
    assert "| worst output / input |" in (out / "stability.md").read_text()


def test_sanitized_counts_are_reported_per_scenario(suite):
    report, _, _ = suite
    scenarios = {s["name"]: s for s in report["scenarios"]}
    assert scenarios["clean"]["sanitized"]["total"] == 0
    color = scenarios["nan_inf_color"]["sanitized"]["non_finite"]
    assert set(color) == {"color", "diffuse", "specular"} and color["color"] > 0
    guides = scenarios["nan_inf_guides"]["sanitized"]["non_finite"]
    assert {"albedo", "normal", "depth", "motion", "jitter"} <= set(guides) and guides["jitter"] == FRAMES // 2


def test_report_files_json_markdown_and_charts(suite):
    report, files, out = suite
    assert json.loads((out / "stability.json").read_text())["methods"][0]["label"] == "identity"
    for name in ("psnr_curves", "psnr_drop", "curve:nan_inf_color"):
        assert files[name].stat().st_size > 1000 and files[name].read_bytes()[:4] == b"\x89PNG"
    markdown = (out / "stability.md").read_text()
    assert "## Where each method fails worst" in markdown and report["definition"] in markdown
    assert "| needs_specular | missing_buffers | FAILED:" in markdown
    assert "![per-frame PSNR](psnr_curves.png)" in markdown and "(curves/garbage_motion.png)" in markdown
    assert "- glass: no sequence of scene 'glass' in the dataset" in markdown
    assert "| nan_inf_color |" in markdown


# --------------------------------------------------------------------------------------------- ghosting

def emitter_frame(index: int, moving: bool = True) -> FrameBundle:
    """A bright 3x3 lamp moving 3 px a frame over a flat dim wall (static camera); the noise-free color is the
    reference, so a per-frame method is exact and any error is history."""
    wall = np.full((SIZE, SIZE, 3), 0.05, np.float32)
    left = 1 + 3 * index if moving else 1
    wall[6:9, left:left + 3] = 4.0
    return FrameBundle(color=wall, albedo=np.full((SIZE, SIZE, 3), 0.5, np.float32),
                       normal=np.broadcast_to(np.array([0, 0, 1], np.float32), (SIZE, SIZE, 3)).copy(),
                       depth=np.ones((SIZE, SIZE), np.float32), motion=np.zeros((SIZE, SIZE, 2), np.float32),
                       jitter=(0.0, 0.0), frame_index=index, references={1: wall.copy()})


def in_memory(name: str, bundles: list[FrameBundle], scale: int = 1) -> Scenario:
    frames = [FrameBatch.from_bundles([b], scale) for b in bundles]
    sequence = EvaluationSequence(name, frames, [False] * len(frames), scale)
    return Scenario(name, SCENE_SCENARIOS.get(name, name), sequence, "memory")


@pytest.fixture(scope="module")
def ghost_suite(tmp_path_factory):
    scenarios = [in_memory("visible_emitter", [emitter_frame(i) for i in range(5)]),
                 in_memory("glass", [emitter_frame(i, moving=False) for i in range(5)])]
    methods = ["identity", BlendWithPrevious("0.5"), BlendWithPrevious("0.2")]
    report = run_suite(scenarios, methods, threads=1)
    out = tmp_path_factory.mktemp("ghosting")
    write_report(report, out)
    return report, out


def test_ghosting_is_measured_where_a_trail_exists_and_names_the_temporal_method_that_ghosts_least(ghost_suite):
    report, _ = ghost_suite
    trails = {s["name"]: s["trail"] for s in report["scenarios"]}
    assert trails["visible_emitter"]["frames"] == 4 and 0 < trails["visible_emitter"]["coverage"] < 1
    assert trails["glass"] == {"frames": 0, "coverage": None, "per_frame_coverage": [0.0] * 5}
    entries = {e["label"]: e for e in report["methods"]}
    identity, half, fifth = entries["identity"], entries["blend:0.5"], entries["blend:0.2"]
    assert not identity["temporal"] and half["temporal"] and fifth["temporal"]
    emitter = {label: entry["scenarios"]["visible_emitter"] for label, entry in entries.items()}
    assert emitter["identity"]["ghost_error"] == 0.0 and emitter["identity"]["ghost_psnr"] == pytest.approx(PSNR_CAP_DB)
    assert emitter["blend:0.5"]["ghost_error"] > emitter["blend:0.2"]["ghost_error"] > 0.01
    assert emitter["blend:0.5"]["per_frame_ghost_error"][0] is None
    assert all(e["scenarios"]["glass"]["ghost_error"] is None for e in entries.values())
    assert report["input"]["visible_emitter"]["ghost_error"] == 0.0  # the noise-free input has no error at all
    ghosting = report["ghosting"]
    assert ghosting["temporal"] == ["blend:0.5", "blend:0.2"] and ghosting["least"] == "blend:0.2"
    assert ghosting["by_scenario"] == {"visible_emitter": "blend:0.2"}
    assert ghosting["common_scenarios"] == ["visible_emitter"]
    assert ghosting["mean_error"]["blend:0.5"] == emitter["blend:0.5"]["ghost_error"]


def test_two_models_of_one_method_keep_their_own_rows_and_ghosting_means():
    entries = [{"label": "fused:balanced", "source": "pretrained:fused-balanced-x1"},
               {"label": "fused:balanced", "source": "runs/a/best.pt"},
               {"label": "oidn-taa:high", "source": "oidn-taa:high"}]
    name_shared_labels(entries)
    assert [e["label"] for e in entries] == ["fused:balanced (pretrained:fused-balanced-x1)",
                                             "fused:balanced (runs/a/best.pt)", "oidn-taa:high"]


def test_ghosting_at_scale_two_measures_the_trail_at_the_reference_resolution():
    bundles = []
    for index in range(5):
        frame = emitter_frame(index)
        double = frame.color.repeat(2, axis=0).repeat(2, axis=1)
        bundles.append(dataclasses.replace(frame, references={2: double}))
    report = run_suite([in_memory("visible_emitter", bundles, scale=2)], [BlendWithPrevious("0.5", scale=2)],
                       scale=2, threads=1)
    trail = report["scenarios"][0]["trail"]
    assert trail["frames"] == 4 and len(report["input"]["visible_emitter"]["per_frame_ghost_error"]) == 5
    assert report["methods"][0]["scenarios"]["visible_emitter"]["ghost_error"] > 0.01


def test_the_report_has_a_ghosting_table(ghost_suite):
    report, out = ghost_suite
    assert json.loads((out / "stability.json").read_text())["ghosting"]["least"] == "blend:0.2"
    markdown = (out / "stability.md").read_text()
    assert "## Ghosting (error inside the trail region; lower is better)" in markdown
    assert report["ghosting"]["definition"] in markdown
    assert "Ghosts least among them: **blend:0.2**" in markdown
    assert "No trail (nothing changed beyond what the motion explains): glass." in markdown
    assert "![ghost error per frame](ghost_curves.png)" in markdown
    assert (out / "ghost_curves.png").read_bytes()[:4] == b"\x89PNG"
    emitter = {e["label"]: e["scenarios"]["visible_emitter"]["ghost_error"] for e in report["methods"]}
    row = (f"| visible_emitter | 4/5 | {report['scenarios'][0]['trail']['coverage']:.1%} | 0.0000 | 0.0000 | "
           f"{emitter['blend:0.5']:.4f} | {emitter['blend:0.2']:.4f} | blend:0.2 |")
    assert row in markdown


# -------------------------------------------------------------------------------------------------- CLI

def test_command_writes_the_report_and_rejects_bad_input(data_dir, tmp_path, capsys):
    out = tmp_path / "report"
    code = main(["stability", "--data", str(data_dir), "--out", str(out), "--method", "identity",
                 "--scenario", "clean", "--scenario", "nan_inf_color", "--frames", "2", "--threads", "1", "--quiet"])
    assert code == 0
    assert "identity: fails worst on no scenario below its median" in capsys.readouterr().out
    report = json.loads((out / "stability.json").read_text())
    assert [s["name"] for s in report["scenarios"]] == ["clean", "nan_inf_color"]
    assert (out / "stability.md").is_file() and (out / "psnr_curves.png").is_file()
    assert main(["stability", "--data", str(data_dir), "--out", str(out), "--method", "nope"]) == 2
    assert "unknown method 'nope'" in capsys.readouterr().err
    assert main(["stability", "--data", str(data_dir), "--out", str(out), "--method", "identity",
                 "--size", "32"]) == 2
    assert "--size applies to --generate only" in capsys.readouterr().err
    (tmp_path / "file").write_text("")
    assert main(["stability", "--data", str(data_dir), "--out", str(tmp_path / "file"),
                 "--method", "identity"]) == 2


@pytest.mark.slow
def test_generate_renders_the_named_scenes_and_reuses_them(tmp_path):
    from model.evaluation.stability import generate_scenarios

    root = generate_scenarios(tmp_path / "data", size=(16, 16), frames=2, ref_spp=4,
                              names=("moving_object", "clean"))
    assert sorted(Dataset(root).names("test")) == ["diffuse_room_s0", "moving_object_s0"]
    messages = []
    generate_scenarios(root, size=(16, 16), frames=2, ref_spp=4, names=("moving_object", "clean"),
                       progress=messages.append)
    assert all(m.startswith("reusing") for m in messages) and len(messages) == 2
    scenarios, _ = build_scenarios(root, names=("moving_object", "clean"))
    assert [s.source for s in scenarios] == ["moving_object_s0", "diffuse_room_s0"]
    report = run_suite(scenarios, [build_method("svgf")])
    assert report["methods"][0]["failures"] == []
