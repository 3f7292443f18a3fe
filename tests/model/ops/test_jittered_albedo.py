"""The albedo gathered on the target grid from jittered frames, and the texture detail it gives a 2x estimate."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from model.ops.jittered_albedo import DETAIL_BOUNDS, gather_samples, sample_weights, splat_at_jitter, texture_detail

SCALE = 2


def fine_checker(size: int = 8) -> torch.Tensor:
    """An albedo checker of one target pixel per square at 2x (N, 3, 2 size, 2 size): finer than a render pixel,
    so every render pixel's mean is the same grey."""
    rows = torch.arange(2 * size).view(-1, 1)
    columns = torch.arange(2 * size).view(1, -1)
    checker = 0.3 + 0.4 * ((rows + columns) % 2).to(torch.float32)
    return checker.expand(1, 3, 2 * size, 2 * size).contiguous()


def sampled(albedo: torch.Tensor, jitter: tuple[float, float]) -> torch.Tensor:
    """What a renderer's albedo guide holds at render resolution for one jitter: the target pixel its sample lies
    in, for every render pixel (a point sample, as the guide is noise-free)."""
    column, row = (int(SCALE * (0.5 + value) // 1) for value in jitter)
    return albedo[:, :, row::SCALE, column::SCALE]


@pytest.mark.parametrize("jitter, sub_pixel", [
    pytest.param((-0.3, -0.2), (0, 0), id="up left"),
    pytest.param((0.3, -0.2), (0, 1), id="up right"),
    pytest.param((-0.1, 0.4), (1, 0), id="down left"),
    pytest.param((0.2, 0.2), (1, 1), id="down right"),
])
def test_a_frame_puts_every_sample_in_the_sub_pixel_its_jitter_points_to(jitter, sub_pixel):
    image = torch.arange(2 * 3 * 4 * 4, dtype=torch.float32).view(2, 3, 4, 4)
    total, weight = splat_at_jitter(image, torch.tensor([jitter, jitter]), SCALE)
    assert total.shape == (2, 3, 8, 8) and weight.shape == (2, 1, 8, 8)
    row, column = sub_pixel
    expected_weight = torch.zeros(2, 1, 8, 8)
    expected_weight[:, :, row::2, column::2] = 1
    torch.testing.assert_close(weight, expected_weight)
    torch.testing.assert_close(total[:, :, row::2, column::2], image)
    assert float(total.sum()) == float(image.sum())  # nothing anywhere else


def test_each_item_of_a_batch_lands_at_its_own_jitter():
    image = torch.ones(2, 1, 2, 2)
    _, weight = splat_at_jitter(image, torch.tensor([[-0.25, -0.25], [0.25, 0.25]]), SCALE)
    assert float(weight[0, 0, 0, 0]) == 1 and float(weight[0, 0, 1, 1]) == 0
    assert float(weight[1, 0, 1, 1]) == 1 and float(weight[1, 0, 0, 0]) == 0


@pytest.mark.parametrize("jitter", [(0.0, 0.0), (0.0, 0.3), (0.3, 0.02), (0.5, 0.25), (-0.5, 0.25)])
def test_a_sample_on_a_sub_pixel_edge_is_not_gathered(jitter):
    # A renderer without jitter writes the pixel centre, which at 2x is the corner of four target pixels.
    _, weight = splat_at_jitter(torch.ones(1, 3, 4, 4), torch.tensor([jitter]), SCALE)
    assert float(weight.sum()) == 0


def test_the_running_mean_is_exact_over_the_first_frames_then_exponential():
    values = [torch.full((1, 1, 2, 2), value) for value in (1.0, 2.0, 3.0, 4.0, 5.0)]
    ones = torch.ones(1, 1, 2, 2)
    total, weight = values[0], ones
    for value in values[1:3]:
        total, weight = gather_samples(total, weight, value, ones, window=3)
    torch.testing.assert_close(total / weight, torch.full_like(ones, 2.0))  # (1 + 2 + 3) / 3
    total, weight = gather_samples(total, weight, values[3], ones, window=3)
    torch.testing.assert_close(weight, torch.full_like(ones, 3.0))  # capped: the old ones weigh 2, the new one 1
    torch.testing.assert_close(total / weight, torch.full_like(ones, (2 * 2.0 + 4.0) / 3))
    with pytest.raises(ValueError, match="whole number of frames"):
        gather_samples(total, weight, values[0], ones, window=0)


def test_four_jittered_frames_give_back_a_texture_finer_than_a_render_pixel():
    albedo = fine_checker()
    total = weight = None
    for jitter in ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25)):
        new_total, new_weight = splat_at_jitter(sampled(albedo, jitter), torch.tensor([jitter]), SCALE)
        total, weight = (new_total, new_weight) if total is None else gather_samples(total, weight, new_total,
                                                                                   new_weight, window=8)
    torch.testing.assert_close(total / weight, albedo)
    # An estimate that holds the render-pixel mean (the same grey everywhere) times the detail is the checker: the
    # ratio is exact, (a + offset) / (mean + offset), trusted n / (n + 2) with one sample per target pixel.
    detail = texture_detail(total, weight, F.interpolate(sampled(albedo, (0.25, 0.25)), scale_factor=2), SCALE)
    ratio = (albedo + 0.02) / (0.5 + 0.02)  # 0.62 and 1.38: within the bounds
    torch.testing.assert_close(detail, 1 + (ratio - 1) / 3)
    dark, light = float(detail.min()), float(detail.max())
    assert dark < 0.9 and light > 1.1  # the squares come back


def test_a_flat_albedo_and_an_empty_gather_leave_the_estimate_as_it_is():
    flat = torch.full((1, 3, 4, 4), 0.5)
    total, weight = splat_at_jitter(flat, torch.tensor([[0.25, -0.25]]), SCALE)
    torch.testing.assert_close(texture_detail(total, weight, F.interpolate(flat, scale_factor=2), SCALE),
                               torch.ones(1, 3, 8, 8))
    checker = fine_checker(4)
    empty = torch.zeros(1, 1, 8, 8)
    torch.testing.assert_close(texture_detail(torch.zeros_like(checker), empty, checker, SCALE),
                               torch.ones_like(checker))


def test_the_detail_is_bounded_where_the_estimate_would_be_far_off():
    albedo = torch.full((1, 1, 4, 4), 0.5)
    albedo[..., 0, 0] = 1.0  # one bright target pixel beside black ones
    albedo[..., 0, 1] = albedo[..., 1, 0] = albedo[..., 1, 1] = 0.0
    detail = texture_detail(albedo * 1000, torch.full_like(albedo, 1000.0), albedo, SCALE)
    assert float(detail.max()) <= DETAIL_BOUNDS[1] + 1e-6 and float(detail.min()) >= DETAIL_BOUNDS[0] - 1e-6


def test_refuses_a_scale_without_a_finer_grid_and_mismatched_shapes():
    with pytest.raises(ValueError, match="scale must be a whole number >= 2"):
        splat_at_jitter(torch.ones(1, 3, 4, 4), torch.zeros(1, 2), 1)
    with pytest.raises(ValueError, match="jitter"):
        splat_at_jitter(torch.ones(1, 3, 4, 4), torch.zeros(2, 2), 2)
    with pytest.raises(ValueError, match="jitter must be"):
        sample_weights(torch.zeros(2), 2, 4, 4)
    with pytest.raises(ValueError, match="scale must be"):
        texture_detail(torch.ones(1, 3, 4, 4), torch.ones(1, 1, 4, 4), torch.ones(1, 3, 4, 4), 1)
