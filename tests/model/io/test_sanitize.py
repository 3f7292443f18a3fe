"""Input sanitizing: NaN/Inf and out-of-range values in -> finite, in-range values out, every repair counted."""

from __future__ import annotations

import math

import pytest
import torch

from model.evaluation.evaluate import EvaluationSequence, run_sequence
from model.methods.base import FrameBatch
from model.methods.registry import build_method, example_batch
from model.io.sanitize import SanitizeReport, sanitize_frame

H = W = 16


def frame(batch: int = 1, seed: int = 0) -> FrameBatch:
    """A valid frame with every optional buffer (diffuse + specular == color)."""
    example = example_batch(H, W, batch=batch, seed=seed)
    return FrameBatch(color=example.diffuse + example.specular, albedo=example.albedo, normal=example.normal,
                      depth=example.depth, motion=example.motion, jitter=torch.full((batch, 2), 0.25),
                      camera_cut=example.camera_cut, diffuse=example.diffuse, specular=example.specular,
                      specular_albedo=example.specular_albedo, roughness=example.roughness)


def assert_all_finite(batch: FrameBatch) -> None:
    for name, tensor in batch.tensors().items():
        if tensor.is_floating_point():
            assert bool(torch.isfinite(tensor).all()), name


def test_a_valid_frame_is_returned_untouched_and_reports_nothing():
    clean = frame()
    repaired, report = sanitize_frame(clean)
    assert repaired is clean and report.clean and report.total == 0 and report.frames == 1
    assert report.to_dict() == {"frames": 1, "total": 0, "non_finite": {}, "out_of_range": {}}
    assert report.describe() == "clean"


@pytest.mark.parametrize("buffer, index, value", [
    ("color", (0, 1, 2, 3), -1e-6), ("albedo", (0, 0, 4, 4), 1.0 + 1e-6), ("roughness", (0, 0, 1, 1), math.nan),
    ("depth", (0, 0, 2, 2), -0.5), ("motion", (0, 1, 5, 5), math.inf), ("normal", (0, 2, 3, 3), 5.0),
])
def test_one_bad_value_anywhere_is_found(buffer, index, value):
    # The quick whole-buffer check must send every kind of bad value to the pixel-wise repairs.
    bad = frame()
    getattr(bad, buffer)[index] = value
    repaired, report = sanitize_frame(bad)
    assert repaired is not bad and getattr(repaired, buffer) is not getattr(bad, buffer)
    assert_all_finite(repaired)
    if buffer == "albedo":  # within the format's tolerance: clamped without being counted
        assert report.total == 0 and float(repaired.albedo[index]) == 1.0
    else:  # radiance has no tolerance: any negative counts
        assert report.total == 1


def test_non_finite_radiance_is_repaired_counted_and_keeps_the_lobe_split():
    clean = frame()
    color, diffuse, specular = clean.color.clone(), clean.diffuse.clone(), clean.specular.clone()
    color[0, :, 0, 0] = math.nan            # color bad, split good: color = diffuse + specular
    color[0, 1, 0, 1] = math.inf            # one bad channel counts the pixel once
    diffuse[0, 2, 1, 0] = math.nan          # split bad, color good: diffuse = color, specular = 0
    specular[0, 0, 2, 0] = -math.inf
    color[0, :, 3, 3] = math.nan            # everything bad: 0 in all three
    diffuse[0, :, 3, 3] = math.inf
    color[0, 0, 5, 5] = -2.0                # negative radiance: clamped, counted as out of range
    repaired, report = sanitize_frame(FrameBatch(**{**clean.tensors(), "color": color, "diffuse": diffuse,
                                                    "specular": specular}))
    assert_all_finite(repaired)
    assert report.non_finite["color"] == 3 and report.non_finite["diffuse"] == 2
    assert report.non_finite["specular"] == 1
    assert report.out_of_range["color"] == 1 and float(repaired.color[0, 0, 5, 5]) == 0.0
    torch.testing.assert_close(repaired.color[0, :, 0, 0], clean.color[0, :, 0, 0])
    torch.testing.assert_close(repaired.diffuse[0, :, 1, 0], clean.color[0, :, 1, 0])
    assert float(repaired.specular[0, :, 1, 0].abs().sum()) == 0.0
    assert float(repaired.color[0, :, 3, 3].abs().sum()) == 0.0
    # Wherever nothing was wrong, nothing changed; and the split still adds up everywhere.
    untouched = torch.ones(H, W, dtype=torch.bool)
    for y, x in ((0, 0), (0, 1), (1, 0), (2, 0), (3, 3), (5, 5)):
        untouched[y, x] = False
    assert torch.equal(repaired.color[0][:, untouched], clean.color[0][:, untouched])
    torch.testing.assert_close((repaired.diffuse + repaired.specular)[..., :5, :5], repaired.color[..., :5, :5])
    assert report.to_dict()["non_finite"] == {"color": 3, "diffuse": 2, "specular": 1}
    assert "color: 3 non-finite, 1 out of range" in report.describe()


def test_color_without_a_split_goes_to_zero_where_not_finite():
    clean = frame()
    color = clean.color.clone()
    color[0, :, 4, 4] = math.nan
    color[0, 0, 7, 2] = math.inf
    repaired, report = sanitize_frame(FrameBatch(**{**clean.tensors(), "color": color, "diffuse": None,
                                                    "specular": None}))
    assert report.non_finite["color"] == 2 and "diffuse" not in report.non_finite
    assert float(repaired.color[0, :, 4, 4].abs().sum()) == 0.0 and float(repaired.color[0, 0, 7, 2]) == 0.0
    assert_all_finite(repaired)


def test_guides_are_repaired_by_their_own_rules():
    clean = frame(batch=2)
    albedo, normal, depth = clean.albedo.clone(), clean.normal.clone(), clean.depth.clone()
    motion, roughness, jitter = clean.motion.clone(), clean.roughness.clone(), clean.jitter.clone()
    albedo[0, 0, 0, 0] = math.nan
    albedo[1, 1, 2, 2] = 1.5                 # out of [0, 1]: clamped and counted
    normal[0, :, 1, 1] = math.inf            # -> (0, 0, 0)
    normal[1, :, 3, 3] = torch.tensor([0.0, 0.0, 2.0])  # not unit length: renormalized and counted
    depth[0, 0, 5, 5] = math.inf             # -> the farthest finite depth of that frame
    depth[1, 0, 6, 6] = math.nan
    depth[1, 0, 7, 7] = -1.0                 # negative -> 0
    motion[0, 1, 8, 8] = math.nan            # -> (0, 0)
    roughness[1, 0, 9, 9] = -math.inf        # -> 1 (diffuse)
    jitter[1, 0] = math.nan                  # -> 0
    batch = FrameBatch(**{**clean.tensors(), "albedo": albedo, "normal": normal, "depth": depth, "motion": motion,
                          "roughness": roughness, "jitter": jitter})
    repaired, report = sanitize_frame(batch)
    assert_all_finite(repaired)
    assert float(repaired.albedo[0, 0, 0, 0]) == 0.0 and float(repaired.albedo[1, 1, 2, 2]) == 1.0
    assert repaired.normal[0, :, 1, 1].tolist() == [0.0, 0.0, 0.0]
    assert repaired.normal[1, :, 3, 3].tolist() == [0.0, 0.0, 1.0]
    finite = clean.depth.clone()
    finite[0, 0, 5, 5] = finite[1, 0, 6, 6] = finite[1, 0, 7, 7] = 0.0  # the replaced pixels do not count
    assert float(repaired.depth[0, 0, 5, 5]) == float(finite[0].amax())
    assert float(repaired.depth[1, 0, 6, 6]) == float(finite[1].amax())
    assert float(repaired.depth[1, 0, 7, 7]) == 0.0
    assert repaired.motion[0, :, 8, 8].tolist() == [0.0, 0.0]
    assert float(repaired.roughness[1, 0, 9, 9]) == 1.0
    assert repaired.jitter[1].tolist() == [0.0, 0.25] and repaired.jitter[0].tolist() == [0.25, 0.25]
    assert report.non_finite == {"color": 0, "diffuse": 0, "specular": 0, "albedo": 1, "specular_albedo": 0,
                                 "roughness": 1, "normal": 1, "depth": 2, "motion": 1, "jitter": 1}
    assert {k: v for k, v in report.out_of_range.items() if v} == {"albedo": 1, "normal": 1, "depth": 1}
    assert report.total == 10 and report.frames == 2


def test_reports_add_up_over_frames():
    one = SanitizeReport({"color": 2}, {"depth": 1}, frames=1)
    two = SanitizeReport({"color": 3, "motion": 4}, {}, frames=1)
    total = one + two
    assert total.non_finite == {"color": 5, "motion": 4} and total.out_of_range == {"depth": 1}
    assert total.frames == 2 and total.total == 10
    assert total.to_dict() == {"frames": 2, "total": 10, "non_finite": {"color": 5, "motion": 4},
                               "out_of_range": {"depth": 1}}


def test_the_evaluation_path_sanitizes_and_counts_per_sequence():
    frames = []
    for index in range(3):
        batch = frame(seed=index)
        color = batch.color.clone()
        color[0, :, index, 0] = math.nan
        frames.append(FrameBatch(**{**batch.tensors(), "color": color, "reference": batch.color.clone()}))
    sequence = EvaluationSequence("corrupt", frames, [False] * 3, scale=1)
    for name in ("identity", "accumulation", "svgf"):
        result = run_sequence(build_method(name).for_inference(), sequence)  # would raise on a non-finite output
        assert result["sanitized"]["non_finite"] == {"color": 3} and result["sanitized"]["frames"] == 3
        assert all(math.isfinite(v) for v in result["per_frame"]["psnr"]) and len(result["per_frame"]["psnr"]) == 3


def test_the_evaluation_report_lists_the_sanitized_counts(tmp_path):
    from model.evaluation.evaluate import evaluate
    from tests.builders import NoisyInput, write_gradient_dataset

    report = evaluate(write_gradient_dataset(tmp_path / "data"), [NoisyInput()], vdp=False, timing_reference=None,
                      frame_limit=2)
    # Data read from disk is validated, so there is nothing to repair; the counts are there all the same.
    assert report["sanitized_inputs"] == {name: {"frames": 2, "total": 0, "non_finite": {}, "out_of_range": {}}
                                          for name in ("a", "b")}
