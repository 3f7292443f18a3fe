"""The comparison picture: panels in order, scores equal to the protocol's, history carried, bad input named."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from model.evaluation.compare import comparison_panels, last_frame_panels, save_comparison
from model.evaluation.evaluate import evaluate
from model.io.dataset import Dataset
from model.methods.base import FrameBatch
from model.evaluation.metrics import frame_metrics
from tests.builders import write_gradient_dataset


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return Dataset(write_gradient_dataset(tmp_path_factory.mktemp("compare") / "data")).sequence("a")


def test_panels_are_input_methods_reference_with_the_protocols_scores(sequence):
    panels = comparison_panels(sequence, ["identity", "accumulation"], frame_index=3, scale=2,
                               labels=[None, "TA + bicubic"])
    assert [p.title for p in panels] == ["input (1spp, bicubic x2)", "identity", "TA + bicubic", "reference x2"]
    assert all(p.image.shape == (32, 32, 3) for p in panels)
    # Accumulation over 4 frames of a static-noise gradient beats the 1spp input; its score is the protocol's.
    assert panels[2].psnr > panels[1].psnr
    frames = [FrameBatch.from_bundles([sequence[i]], 2) for i in range(4)]
    from model.methods.registry import build_method

    method, state = build_method("accumulation", 2).eval(), None
    with torch.no_grad():
        for frame in frames:
            output, state = method.step(frame.without_reference(), state)
    assert panels[2].psnr == pytest.approx(float(frame_metrics(output, frames[-1].reference)["psnr"][0]), abs=1e-4)
    expected_reference = np.clip(sequence[3].reference(2), 0, 1) ** (1 / 2.2)
    assert panels[-1].psnr is None and np.allclose(panels[-1].image, expected_reference, atol=1e-5)


def test_bad_frame_scale_and_zoom_are_named(sequence, tmp_path):
    with pytest.raises(ValueError, match="frame 9 is outside sequence 'a'"):
        comparison_panels(sequence, ["identity"], frame_index=9, scale=1)
    panels = comparison_panels(sequence, ["identity"], frame_index=0, scale=1)
    with pytest.raises(ValueError, match="does not fit the 16x16 output"):
        save_comparison(panels, tmp_path / "x.png", zoom=(10, 10, 8))
    out = save_comparison(panels, tmp_path / "sub" / "x.png", title="t", zoom=(2, 2, 8))
    assert Path(out).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_an_evaluations_last_outputs_give_the_picture_a_rerun_gives(tmp_path):
    """The evaluation hands each sequence's last-frame outputs over; drawn, they equal a separate run to that frame."""
    root = write_gradient_dataset(tmp_path / "data")
    drawn = {}

    def draw(evaluated, outputs):
        drawn[evaluated.name] = last_frame_panels(evaluated, outputs)

    evaluate(root, ["identity", "accumulation"], scale=2, frame_limit=3, vdp=False, timing_reference=None,
             inference_forms="off", last_outputs=draw)
    assert sorted(drawn) == ["a", "b"]
    rerun = comparison_panels(Dataset(root).sequence("a"), ["identity", "accumulation"], frame_index=2, scale=2)
    assert [p.title for p in drawn["a"]] == [p.title for p in rerun]
    for got, want in zip(drawn["a"], rerun):
        assert np.allclose(got.image, want.image, atol=1e-6) and got.psnr == pytest.approx(want.psnr, abs=1e-6)
    assert drawn["a"][2].psnr > drawn["a"][1].psnr  # accumulation over 3 frames beats one noisy frame
