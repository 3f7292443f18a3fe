"""scaled_bicubic / scaled_nearest against F.grid_sample on the same grid (itself checked against per-pixel loops in
test_warp), and the cubic kernel against its closed form."""

import pytest
import torch
import torch.nn.functional as F

from model.ops.separable_sample import cubic_kernel, scaled_bicubic, scaled_nearest


def _grid_sample(image, shift, scale, mode):
    # the grid the resample reads: output pixel X at source pixel (X + 0.5) / scale - 0.5 + shift, normalised
    n, _, h, w = image.shape
    xs = (torch.arange(w * scale, dtype=image.dtype) + 0.5) / scale
    ys = (torch.arange(h * scale, dtype=image.dtype) + 0.5) / scale
    gx = 2 * (xs.view(1, -1) + shift[:, :1].to(image.dtype)) / w - 1
    gy = 2 * (ys.view(1, -1) + shift[:, 1:].to(image.dtype)) / h - 1
    size = (n, h * scale, w * scale)
    grid = torch.stack([gx.view(n, 1, -1).expand(size), gy.view(n, -1, 1).expand(size)], dim=-1)
    return F.grid_sample(image, grid, mode=mode, padding_mode="border", align_corners=False)


# shifts at both limits, quarters (where nearest reads are ties half-way between two pixels), zero and arbitrary
SHIFTS = [(0.5, -0.5), (-0.5, 0.5), (0.25, -0.25), (0.0, 0.0), (-0.25, 0.125), (0.37, -0.41)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("scale", [1, 2, 3])
@pytest.mark.parametrize("shape", [(6, 3, 9, 11), (6, 1, 16, 16), (6, 2, 12, 10)])
def test_scaled_reads_match_grid_sample(shape, scale, dtype):
    generator = torch.Generator().manual_seed(sum(shape) + scale)
    image = torch.rand(*shape, generator=generator, dtype=torch.float64).to(dtype)
    shift = torch.tensor(SHIFTS, dtype=dtype)  # one per item: each item reads at its own shift
    torch.testing.assert_close(scaled_bicubic(image, shift, scale), _grid_sample(image, shift, scale, "bicubic"))
    torch.testing.assert_close(scaled_nearest(image, shift, scale), _grid_sample(image, shift, scale, "nearest"),
                               rtol=0, atol=0)


def test_a_whole_pixel_read_returns_the_pixel():
    image = torch.rand(1, 3, 6, 6, dtype=torch.float64)
    shift = torch.tensor([[0.0, 0.0]], dtype=torch.float64)
    # at scale 1 and no shift every position is a pixel centre, where cubic convolution reads the pixel itself
    torch.testing.assert_close(scaled_bicubic(image, shift, 1), image)
    torch.testing.assert_close(scaled_nearest(image, shift, 1), image, rtol=0, atol=0)


def test_cubic_kernel_is_the_closed_form():
    d = torch.tensor([0.0, 0.5, 1.0, 1.5, 2.0, 2.5, -0.5, -1.5], dtype=torch.float64)
    # A = -0.75: K(0) = 1, K(0.5) = 0.59375, K(1) = 0, K(1.5) = -0.09375, 0 from 2 on, even in d
    expected = torch.tensor([1.0, 0.59375, 0.0, -0.09375, 0.0, 0.0, 0.59375, -0.09375], dtype=torch.float64)
    torch.testing.assert_close(cubic_kernel(d), expected)
    t = torch.linspace(0, 0.999, 17, dtype=torch.float64).unsqueeze(-1)
    taps = torch.arange(-1, 3, dtype=torch.float64)
    torch.testing.assert_close(cubic_kernel(t - taps).sum(dim=-1), torch.ones(17, dtype=torch.float64))


def test_taps_past_the_border_read_the_edge_pixel():
    image = torch.tensor([[[[1.0, 2.0, 4.0, 8.0]]]], dtype=torch.float64)
    # scale 1, shift -0.5: pixel 0 reads at -0.5, taps -2, -1, 0, 1 (t = 0.5): the first three read pixel 0
    out = scaled_bicubic(image, torch.tensor([[-0.5, 0.0]], dtype=torch.float64), 1)
    expected = (-0.09375 + 0.59375 + 0.59375) * 1.0 - 0.09375 * 2.0
    torch.testing.assert_close(out[0, 0, 0, 0], torch.tensor(expected, dtype=torch.float64))


def test_a_shift_past_half_a_pixel_is_clamped_to_it():
    image = torch.rand(1, 2, 8, 8, dtype=torch.float64)
    far, limit = torch.tensor([[3.0, -2.0]], dtype=torch.float64), torch.tensor([[0.5, -0.5]], dtype=torch.float64)
    torch.testing.assert_close(scaled_bicubic(image, far, 2), scaled_bicubic(image, limit, 2))
    torch.testing.assert_close(scaled_nearest(image, far, 2), scaled_nearest(image, limit, 2))


def test_bad_shapes_and_scales_are_refused_with_them():
    with pytest.raises(ValueError, match=r"shift must be \(N, 2\) with N = 2"):
        scaled_bicubic(torch.zeros(2, 3, 4, 4), torch.zeros(1, 2), 2)
    with pytest.raises(ValueError, match=r"\(N, C, H, W\)"):
        scaled_nearest(torch.zeros(3, 4, 4), torch.zeros(1, 2), 2)
    with pytest.raises(ValueError, match="scale must be a whole number >= 1, got 0"):
        scaled_bicubic(torch.zeros(1, 3, 4, 4), torch.zeros(1, 2), 0)
