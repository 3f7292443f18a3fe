"""Losses: closed-form values on tiny tensors, frame weights, tone maps, finiteness and gradients."""

from __future__ import annotations

import math

import pytest
import torch

from model.training.losses import SequenceLoss, smape, temporal_gradient_l1, tonemap


def constant(value: float) -> torch.Tensor:
    return torch.full((1, 3, 2, 2), value)


def test_smape_has_its_closed_form():
    # |2 - 1| / (2 + 1 + 0.01) at every element.
    assert float(smape(constant(2.0), constant(1.0))) == pytest.approx(1 / 3.01)
    assert float(smape(constant(0.5), constant(0.5))) == 0.0
    # Symmetric in its arguments, and scale-free up to eps.
    assert float(smape(constant(1.0), constant(2.0))) == pytest.approx(float(smape(constant(2.0), constant(1.0))))
    assert float(smape(constant(200.0), constant(100.0), eps=0.0)) == pytest.approx(1 / 3)


def test_temporal_gradient_l1_compares_changes_not_values():
    # Output is off by a constant 0.5 in both frames: no flicker, so no temporal loss.
    assert float(temporal_gradient_l1(constant(1.5), constant(0.5), constant(1.0), constant(0.0))) == 0.0
    # Output changes by 1, the target by 0.25.
    assert float(temporal_gradient_l1(constant(1.0), constant(0.0), constant(0.25), constant(0.0))) == 0.75


def test_sequence_loss_weights_frames_and_terms():
    outputs = [constant(1.0), constant(2.0), constant(2.0)]
    targets = [constant(1.0), constant(1.0), constant(2.0)]
    loss = SequenceLoss(spatial_weight=2.0, temporal_weight=3.0, tonemap="linear", frame_weights=[1, 1, 2], eps=0.0)
    terms = loss(outputs, targets)
    spatial = (0 + 1 * (1 / 3) + 2 * 0) / 4
    temporal = (1 * 1.0 + 2 * 1.0) / 3  # t=1: change 1 vs 0; t=2: change 0 vs 1
    assert float(terms.spatial) == pytest.approx(spatial)
    assert float(terms.temporal) == pytest.approx(temporal)
    assert float(terms.total) == pytest.approx(2 * spatial + 3 * temporal)


def test_zero_weight_frames_do_not_count():
    good, bad = constant(1.0), constant(50.0)
    loss = SequenceLoss(tonemap="log", frame_weights=[0, 1])
    terms = loss([bad, good], [good, good])
    assert float(terms.spatial) == 0.0
    # Frame 1's temporal term still sees frame 0's output (the change from 50 to 1).
    assert float(terms.temporal) > 0


def test_one_frame_has_no_temporal_term():
    terms = SequenceLoss()([constant(1.0)], [constant(2.0)])
    assert float(terms.temporal) == 0.0 and float(terms.total) == pytest.approx(float(terms.spatial))


@pytest.mark.parametrize("kind, expected", [("linear", 9.0), ("log", math.log1p(9.0)),
                                            ("mulaw", math.log1p(5000 * 9.0) / math.log1p(5000))])
def test_tonemaps_are_sign_preserving(kind, expected):
    x = torch.tensor([9.0, -9.0, 0.0])
    mapped = tonemap(x, kind)
    assert mapped.tolist() == pytest.approx([expected, -expected, 0.0])


def test_log_tonemap_makes_highlight_flicker_cost_by_its_relative_size():
    mid, bright = constant(10.0), constant(1000.0)
    linear, log = SequenceLoss(tonemap="linear"), SequenceLoss(tonemap="log")

    def flicker(loss: SequenceLoss, level: torch.Tensor) -> float:  # the same 10 % flicker at a given level
        return float(loss([level, level * 1.1], [level, level]).temporal)

    # On linear radiance the highlight's flicker costs 100x more; after the log map about the same.
    assert flicker(linear, bright) / flicker(linear, mid) == pytest.approx(100, rel=1e-3)
    assert flicker(log, bright) / flicker(log, mid) == pytest.approx(1.0, abs=0.15)


def test_loss_is_finite_with_gradients_for_negative_outputs():
    output = torch.tensor([[-2.0, 0.5, 3.0]]).view(1, 3, 1, 1).requires_grad_()
    target = torch.tensor([[0.0, 0.5, 1.0]]).view(1, 3, 1, 1)
    terms = SequenceLoss()([output, output * 1.0], [target, target])
    terms.total.backward()
    assert torch.isfinite(terms.total) and torch.isfinite(output.grad).all()
    assert output.grad[0, 0, 0, 0] < 0  # gradient descent moves the negative output up, towards 0


def test_display_term_is_the_weighted_mse_psnr_measures():
    outputs = [constant(0.25), constant(4.0), constant(0.5)]
    targets = [constant(0.0), constant(1.0), constant(0.25)]
    loss = SequenceLoss(spatial_weight=0.0, temporal_weight=0.0, frame_weights=[1, 1, 2], display_weight=10.0)
    terms = loss(outputs, targets)
    gamma = 1 / 2.2
    # Frame 1 is clipped to 1 on both sides (the display shows no difference).
    per_frame = [0.25 ** gamma, 0.0, 0.5 ** gamma - 0.25 ** gamma]
    expected = (per_frame[0] ** 2 + 2 * per_frame[2] ** 2) / 4
    assert float(terms.display) == pytest.approx(expected, rel=1e-5)
    assert float(terms.total) == pytest.approx(10 * expected, rel=1e-5)
    assert terms.detached()["display_loss"] == pytest.approx(expected, rel=1e-5)


def test_no_display_term_by_default():
    terms = SequenceLoss()([constant(0.5)], [constant(0.25)])
    assert terms.display is None and "display_loss" not in terms.detached()


@pytest.mark.parametrize("kwargs, message", [
    ({"tonemap": "srgb"}, "unknown tone map"),
    ({"frame_weights": [0, 0]}, "positive sum"),
    ({"spatial_weight": -1}, ">= 0"),
    ({"display_weight": -0.5}, "display -0.5"),
])
def test_bad_settings_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        SequenceLoss(**kwargs)


def test_frame_count_must_match_weights():
    with pytest.raises(ValueError, match="2 frame weights for a sequence of 3"):
        SequenceLoss(frame_weights=[1, 1])([constant(1.0)] * 3, [constant(1.0)] * 3)
