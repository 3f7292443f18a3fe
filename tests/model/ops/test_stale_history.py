"""The stale-history test: how many standard errors a history's window mean lies from the 1 spp frame's, and the
root mean square of those distances over a region."""

from __future__ import annotations

import math

import pytest
import torch

from model.ops.stale_history import (
    REGION_SIGMAS,
    REGION_Z_CAP,
    RELATIVE_FLOOR,
    history_trust,
    regional_z,
    stale_history_trust,
    stale_history_z,
)
from tests.builders import noisy_constant


def naive_z(noisy: torch.Tensor, history: torch.Tensor, block: int) -> torch.Tensor:
    """Each pixel's window (cut at the border), its values and spread, one pixel at a time."""
    value, past = noisy.mean(dim=1)[0], history.mean(dim=1)[0]
    h, w = value.shape
    radius = block // 2
    out = torch.zeros(1, 1, h, w, dtype=torch.float64)
    for y in range(h):
        for x in range(w):
            window = value[max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1].double()
            past_mean = past[max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1].double().mean()
            variance = (window * window).mean() - window.mean() ** 2  # population variance, as the op
            error = math.sqrt(float(variance) / block ** 2 + float(RELATIVE_FLOOR * past_mean) ** 2 + 1e-6)
            out[0, 0, y, x] = abs(float(window.mean() - past_mean)) / error
    return out


@pytest.mark.parametrize("block", [1, 3, 5])
def test_z_matches_a_naive_loop_over_each_window(block):
    generator = torch.Generator().manual_seed(3)
    noisy = torch.rand(1, 3, 7, 9, generator=generator) * 2
    history = torch.rand(1, 3, 7, 9, generator=generator)
    torch.testing.assert_close(stale_history_z(noisy, history, block).double(), naive_z(noisy, history, block),
                               atol=1e-4, rtol=1e-4)


def test_an_unbiased_frame_passes_and_a_changed_light_fails():
    truth = torch.full((1, 3, 48, 48), 0.5)
    noisy = noisy_constant(truth, torch.Generator().manual_seed(0))  # relative standard deviation 0.58
    still = stale_history_z(noisy, truth, 9)
    assert float((still > 3).float().mean()) < 0.01  # noise alone: rarely past 3 standard errors
    brighter = stale_history_z(noisy * 1.5, truth, 9)  # the light got 50% brighter: about 7.7 standard errors
    assert float(brighter.min()) > 5
    dimmer = stale_history_z(noisy, truth * 1.5, 9)
    assert float(dimmer.min()) > 3


def test_a_firefly_widens_the_error_so_it_does_not_read_as_a_change():
    truth = torch.full((1, 3, 27, 27), 0.5)
    noisy = noisy_constant(truth, torch.Generator().manual_seed(1))
    noisy[:, :, 13, 13] = 400.0  # one sample with most of the window's energy
    assert float(stale_history_z(noisy, truth, 9)[0, 0, 13, 13]) < 1.5


def test_trust_is_full_up_to_the_threshold_and_falls_off_past_it():
    z = torch.tensor([0.0, 2.0, 3.0, 4.0])
    torch.testing.assert_close(history_trust(z, 2.0), torch.tensor([1.0, 1.0, math.exp(-0.5), math.exp(-2.0)]))


@pytest.mark.parametrize("shapes, block, message", [
    (((1, 3, 8, 8), (1, 3, 8, 9)), 3, "one shape"),
    (((1, 1, 8, 8), (1, 1, 8, 8)), 3, r"\(N, 3, H, W\)"),
    (((1, 3, 8, 8), (1, 3, 8, 8)), 4, "odd"),
    (((1, 3, 8, 8), (1, 3, 8, 8)), 0, "odd and positive"),
])
def test_bad_shapes_and_blocks_are_refused(shapes, block, message):
    with pytest.raises(ValueError, match=message):
        stale_history_z(torch.ones(shapes[0]), torch.ones(shapes[1]), block)


@pytest.mark.parametrize("window", [1, 3, 7])
def test_the_regional_z_is_the_root_mean_square_of_each_window_cut_at_the_border(window):
    z = torch.rand(1, 1, 6, 8, generator=torch.Generator().manual_seed(4)) * 3
    radius = window // 2
    expected = torch.zeros_like(z)
    for y in range(6):
        for x in range(8):
            part = z[0, 0, max(0, y - radius):y + radius + 1, max(0, x - radius):x + radius + 1]
            expected[0, 0, y, x] = part.square().mean().sqrt()
    torch.testing.assert_close(regional_z(z, window, cap=3.0), expected)  # z stays under 3 here
    torch.testing.assert_close(regional_z(torch.full((1, 1, 5, 5), 2.5), 33), torch.full((1, 1, 5, 5), 2.5))


def test_a_few_windows_far_off_do_not_speak_for_their_region():
    z = torch.full((1, 1, 33, 33), 0.8)  # no change: z's about as small as large
    z[..., 12:21, 12:21] = 40.0  # a visible lamp moved: 81 of the region's 1089 windows are sure
    capped = float(regional_z(z, 33)[0, 0, 16, 16])
    assert capped == pytest.approx(math.sqrt((81 * REGION_Z_CAP ** 2 + 1008 * 0.64) / 1089), rel=1e-4)
    uncapped = regional_z(z, 33, cap=float("inf"))[0, 0, 16, 16]
    assert float(history_trust(torch.tensor(capped), REGION_SIGMAS)) > 0.98  # the region keeps its history
    assert float(history_trust(uncapped, REGION_SIGMAS)) < 0.01  # uncapped, the lamp alone would throw it away


def test_a_small_change_everywhere_fails_the_regional_test_where_single_windows_pass():
    truth = torch.full((1, 3, 48, 48), 0.5)
    generator = torch.Generator().manual_seed(5)
    brighter = noisy_constant(truth * 1.1, generator)  # about 1.9 standard errors a window: under a 3-sigma test
    same = noisy_constant(truth, generator)
    alone = stale_history_trust(brighter, truth, 3.0)
    torch.testing.assert_close(alone, history_trust(stale_history_z(brighter, truth), 3.0))
    assert float(alone.mean()) > 0.9  # few single windows are sure
    regional = stale_history_trust(brighter, truth, 3.0, region=33)
    assert float(regional.mean()) < 0.75  # the regions are
    assert torch.all(regional <= alone)  # the lesser of the two trusts
    assert float(stale_history_trust(same, truth, 3.0, region=33).mean()) > 0.97  # noise alone passes both
    assert 1.0 < REGION_SIGMAS < 2.0  # past the root mean square of z's under no change (about 1)


@pytest.mark.parametrize("shape, window, message", [
    ((1, 3, 8, 8), 3, r"\(N, 1, H, W\)"),
    ((1, 1, 8, 8), 4, "odd and positive"),
    ((1, 1, 8, 8), 0, "odd and positive"),
])
def test_a_regional_z_of_another_shape_or_an_even_window_is_refused(shape, window, message):
    with pytest.raises(ValueError, match=message):
        regional_z(torch.ones(shape), window)
