"""separable_bicubic / separable_nearest against F.grid_sample on the same grid (itself checked against per-pixel
loops in test_warp), and the cubic weights against their closed form."""

import pytest
import torch
import torch.nn.functional as F

from model.ops.separable_sample import cubic_weights, separable_bicubic, separable_nearest


def _grid_sample(image, gx, gy, mode):
    n = image.shape[0]
    size = (n, gy.shape[1], gx.shape[1])
    grid = torch.stack([gx.view(n, 1, -1).expand(size), gy.view(n, -1, 1).expand(size)], dim=-1)
    return F.grid_sample(image, grid, mode=mode, padding_mode="border", align_corners=False)


def _normalised(n, count, size, generator, dtype):
    # inside, past both borders by up to 2 pixels, and exact halves (where nearest rounds to even)
    pixels = torch.rand(n, count, generator=generator, dtype=torch.float64) * (size + 3) - 2
    pixels[:, :4] = torch.tensor([-0.5, 0.5, 1.5, size - 1.5], dtype=torch.float64)
    return ((2 * pixels + 1) / size - 1).to(dtype)


def _pixels(normalised, size):
    return (normalised + 1) * (size / 2) - 0.5  # grid_sample's own unnormalisation (align_corners=False)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("shape", [(1, 3, 9, 11), (2, 6, 7, 5), (3, 1, 16, 16)])
def test_separable_reads_match_grid_sample(shape, dtype):
    generator = torch.Generator().manual_seed(sum(shape))
    n, c, h, w = shape
    image = torch.rand(*shape, generator=generator, dtype=torch.float64).to(dtype)
    gx, gy = _normalised(n, 2 * w + 1, w, generator, dtype), _normalised(n, 2 * h - 1, h, generator, dtype)
    x, y = _pixels(gx, w), _pixels(gy, h)
    torch.testing.assert_close(separable_bicubic(image, x, y), _grid_sample(image, gx, gy, "bicubic"))
    torch.testing.assert_close(separable_nearest(image, x, y), _grid_sample(image, gx, gy, "nearest"),
                               rtol=0, atol=0)


def test_each_item_reads_at_its_own_positions():
    image = torch.rand(2, 3, 6, 6, dtype=torch.float64)
    x = torch.tensor([[0.0, 2.0], [3.0, 5.0]], dtype=torch.float64)
    y = torch.tensor([[1.0], [4.0]], dtype=torch.float64)
    out = separable_bicubic(image, x, y)  # whole pixels: cubic convolution reads the pixel itself
    torch.testing.assert_close(out[0, :, 0], image[0, :, 1, [0, 2]])
    torch.testing.assert_close(out[1, :, 0], image[1, :, 4, [3, 5]])


def test_cubic_weights_sum_to_one_and_interpolate():
    t = torch.linspace(0, 0.999, 17, dtype=torch.float64)
    weights = cubic_weights(t)
    torch.testing.assert_close(weights.sum(dim=-1), torch.ones_like(t))
    torch.testing.assert_close(cubic_weights(torch.zeros(1, dtype=torch.float64))[0],
                               torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=torch.float64))
    # A = -0.75 at t = 0.5: the closed form gives -0.09375, 0.59375, 0.59375, -0.09375
    torch.testing.assert_close(cubic_weights(torch.tensor([0.5], dtype=torch.float64))[0],
                               torch.tensor([-0.09375, 0.59375, 0.59375, -0.09375], dtype=torch.float64))


def test_taps_past_the_border_read_the_edge_pixel():
    image = torch.tensor([[[[1.0, 2.0, 4.0, 8.0]]]], dtype=torch.float64)
    # at -0.5 the taps are -2, -1, 0, 1 (t = 0.5): the first three read pixel 0
    out = separable_bicubic(image, torch.tensor([[-0.5]], dtype=torch.float64), torch.zeros(1, 1, dtype=torch.float64))
    expected = (-0.09375 + 0.59375 + 0.59375) * 1.0 - 0.09375 * 2.0
    torch.testing.assert_close(out.flatten(), torch.tensor([expected], dtype=torch.float64))


def test_bad_shapes_are_refused_with_the_shapes():
    with pytest.raises(ValueError, match=r"\(N, W_out\)"):
        separable_bicubic(torch.zeros(2, 3, 4, 4), torch.zeros(1, 8), torch.zeros(2, 8))
    with pytest.raises(ValueError, match=r"\(N, C, H, W\)"):
        separable_nearest(torch.zeros(3, 4, 4), torch.zeros(1, 8), torch.zeros(1, 8))
