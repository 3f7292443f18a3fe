"""The running mean of the 1 spp frames: a plain mean, then an exponential one, restarted where it is stale."""

from __future__ import annotations

import pytest
import torch

from model.ops.sample_mean import JITTERED_SPREAD_SHARE, sample_mean_spread, update_sample_mean
from model.ops.warp import bilinear_spread
from tests.builders import noisy_constant

SHAPE = (1, 3, 12, 12)


def _run(frames, valid=None, max_frames=4, sigmas=0.0):
    mean = count = None
    for frame in frames:
        if mean is None:
            mean, count = frame, torch.ones(1, 1, *frame.shape[2:])
            continue
        ok = torch.ones_like(count, dtype=torch.bool) if valid is None else valid
        mean, count = update_sample_mean(frame, mean, count, ok, max_frames, sigmas)
    return mean, count


def test_the_mean_of_the_first_frames_then_a_fixed_share_for_each_new_one():
    generator = torch.Generator().manual_seed(0)
    frames = [torch.rand(SHAPE, generator=generator) * 2 for _ in range(6)]
    mean, count = _run(frames[:3])
    torch.testing.assert_close(mean, sum(frames[:3]) / 3)
    expected = sum(frames[:4]) / 4
    for frame in frames[4:]:  # past 4 frames every new one weighs a quarter
        expected = frame / 4 + expected * 3 / 4
    mean, count = _run(frames)
    torch.testing.assert_close(mean, expected)
    assert torch.all(count == 4)


def test_an_invalid_history_restarts_at_the_new_frame():
    generator = torch.Generator().manual_seed(1)
    previous, frame = torch.rand(SHAPE, generator=generator), torch.rand(SHAPE, generator=generator)
    valid = torch.ones(1, 1, 12, 12, dtype=torch.bool)
    valid[..., :6] = False
    mean, count = update_sample_mean(frame, previous, torch.full((1, 1, 12, 12), 3.0), valid, 8)
    torch.testing.assert_close(mean[..., :6], frame[..., :6])
    torch.testing.assert_close(mean[..., 6:], (frame[..., 6:] + 3 * previous[..., 6:]) / 4)
    assert torch.all(count[..., :6] == 1) and torch.all(count[..., 6:] == 4)


def test_a_changed_light_restarts_the_mean_and_noise_alone_does_not():
    truth = torch.full((1, 3, 32, 32), 0.5)
    generator = torch.Generator().manual_seed(2)
    history, count = truth.clone(), torch.full((1, 1, 32, 32), 4.0)
    valid = torch.ones_like(count, dtype=torch.bool)
    brighter = noisy_constant(truth * 3, generator)
    mean, new_count = update_sample_mean(brighter, history, count, valid, 8, stale_sigmas=2.0)
    torch.testing.assert_close(mean, brighter, atol=1e-4, rtol=1e-4)
    assert float(new_count.max()) < 1.001
    same = noisy_constant(truth, generator)
    _, kept = update_sample_mean(same, history, count, valid, 8, stale_sigmas=2.0)
    assert float(kept.mean()) > 4.9  # 5 frames nearly everywhere


def test_with_a_region_a_small_change_everywhere_restarts_the_mean_too():
    truth = torch.full((1, 3, 48, 48), 0.5)
    generator = torch.Generator().manual_seed(3)
    history, count = truth.clone(), torch.full((1, 1, 48, 48), 4.0)
    valid = torch.ones_like(count, dtype=torch.bool)
    brighter = noisy_constant(truth * 1.1, generator)  # under 2 standard errors in most single windows
    _, alone = update_sample_mean(brighter, history, count, valid, 8, stale_sigmas=2.0)
    _, regional = update_sample_mean(brighter, history, count, valid, 8, stale_sigmas=2.0, stale_region=33)
    assert float(alone.mean()) > 4.4 and float(regional.mean()) < 0.8 * float(alone.mean())
    _, kept = update_sample_mean(noisy_constant(truth, generator), history, count, valid, 8, stale_sigmas=2.0,
                                 stale_region=33)
    assert float(kept.mean()) > 4.9  # noise alone keeps nearly every frame


def test_a_window_below_one_frame_is_refused():
    with pytest.raises(ValueError, match="max_frames must be >= 1"):
        update_sample_mean(torch.ones(SHAPE), torch.ones(SHAPE), torch.ones(1, 1, 12, 12),
                           torch.ones(1, 1, 12, 12, dtype=torch.bool), 0)


def test_guides_after_the_colour_are_averaged_with_its_weights_and_do_not_restart_it():
    generator = torch.Generator().manual_seed(3)
    colour = torch.full((1, 3, 16, 16), 0.5)
    previous = torch.cat([colour, torch.full((1, 6, 16, 16), 0.2)], dim=1)
    frame = torch.cat([noisy_constant(colour, generator), torch.full((1, 6, 16, 16), 0.8)], dim=1)
    count = torch.full((1, 1, 16, 16), 3.0)
    valid = torch.ones_like(count, dtype=torch.bool)
    mean, new_count = update_sample_mean(frame, previous, count, valid, 8, stale_sigmas=2.0)
    _, colour_count = update_sample_mean(frame[:, :3], previous[:, :3], count, valid, 8, stale_sigmas=2.0)
    torch.testing.assert_close(new_count, colour_count)  # the guides quadrupled: the test reads the colour alone
    assert float(new_count.mean()) > 3.9
    torch.testing.assert_close(mean, frame / new_count + (1 - 1 / new_count) * previous)
    kept = (new_count == 4).expand(1, 6, 16, 16)
    torch.testing.assert_close(mean[:, 3:][kept], torch.full_like(mean[:, 3:][kept], 0.35))


def test_samples_of_another_shape_or_without_a_colour_are_refused():
    ok = torch.ones(1, 1, 12, 12, dtype=torch.bool)
    with pytest.raises(ValueError, match="one shape"):
        update_sample_mean(torch.ones(1, 9, 12, 12), torch.ones(1, 3, 12, 12), torch.ones(1, 1, 12, 12), ok, 4)
    with pytest.raises(ValueError, match="C >= 3"):
        update_sample_mean(torch.ones(1, 2, 12, 12), torch.ones(1, 2, 12, 12), torch.ones(1, 1, 12, 12), ok, 4)


def test_a_blurring_read_keeps_the_frames_its_spread_leaves():
    generator = torch.Generator().manual_seed(4)
    previous, frame = torch.rand(SHAPE, generator=generator), torch.rand(SHAPE, generator=generator)
    valid = torch.ones(1, 1, 12, 12, dtype=torch.bool)
    spread = torch.zeros(1, 1, 12, 12)
    spread[..., :4], spread[..., 4:8] = 1.0, 0.5  # half a pixel on both axes; on one
    mean, count = update_sample_mean(frame, previous, torch.full((1, 1, 12, 12), 4.0), valid, 8, spread=spread)
    assert count[..., :4].eq(1).all() and count[..., 4:8].eq(3).all() and count[..., 8:].eq(5).all()
    torch.testing.assert_close(mean[..., :4], frame[..., :4])  # restarted
    torch.testing.assert_close(mean[..., 4:8], (frame[..., 4:8] + 2 * previous[..., 4:8]) / 3)
    torch.testing.assert_close(mean[..., 8:], (frame[..., 8:] + 4 * previous[..., 8:]) / 5)
    with pytest.raises(ValueError, match="spread must have the count's shape"):
        update_sample_mean(frame, previous, torch.ones(1, 1, 12, 12), valid, 8, spread=torch.zeros(1, 1, 6, 6))


def test_the_warp_s_blur_counts_in_full_without_jitter_and_in_part_with_it():
    motion = torch.full((3, 2, 4, 4), 0.5)
    jitter = torch.tensor([[0.0, 0.0], [0.25, 0.0], [0.0, 0.0]])
    previous = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, -0.1]])  # the third was jittered a frame ago
    spread = sample_mean_spread(motion, jitter, previous)
    torch.testing.assert_close(spread[0], bilinear_spread(motion)[0])
    torch.testing.assert_close(spread[1:], JITTERED_SPREAD_SHARE * bilinear_spread(motion)[1:])
