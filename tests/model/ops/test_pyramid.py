"""block_mean / downsample2x / upsample2x / build_pyramid against per-pixel loops, the pooling they replace and
identities."""

import math

import pytest
import torch

import torch.nn.functional as F

from model.ops.pyramid import block_mean, build_pyramid, downsample2x, upsample2x
from tests.builders import rand


def naive_down(x):
    n_, c_, h, w = x.shape
    out = torch.zeros(n_, c_, (h + 1) // 2, (w + 1) // 2, dtype=x.dtype)
    for y in range(out.shape[-2]):
        for xx in range(out.shape[-1]):
            # replicate-padding: a missing row/column repeats the last one
            taps = [x[..., min(2 * y + dy, h - 1), min(2 * xx + dx, w - 1)] for dy in (0, 1) for dx in (0, 1)]
            out[..., y, xx] = sum(taps) / 4
    return out


def naive_up_bilinear(x):
    n_, c_, h, w = x.shape
    out = torch.zeros(n_, c_, 2 * h, 2 * w, dtype=x.dtype)

    def src(i, size):
        s = max((i + 0.5) / 2 - 0.5, 0.0)  # fine centre -> coarse index space, clamped at the border
        i0 = min(math.floor(s), size - 1)
        return i0, min(i0 + 1, size - 1), s - i0

    for y in range(2 * h):
        y0, y1, ty = src(y, h)
        for xx in range(2 * w):
            x0, x1, tx = src(xx, w)
            out[..., y, xx] = (
                (1 - ty) * ((1 - tx) * x[..., y0, x0] + tx * x[..., y0, x1])
                + ty * ((1 - tx) * x[..., y1, x0] + tx * x[..., y1, x1])
            )
    return out


@pytest.mark.parametrize("shape", [(12, 10), (11, 9)])
def test_downsample_matches_naive(shape):
    x = rand(2, 3, *shape, seed=1)
    torch.testing.assert_close(downsample2x(x), naive_down(x))


def test_upsample_matches_naive():
    x = rand(2, 3, 6, 5, seed=2)
    torch.testing.assert_close(upsample2x(x, "bilinear"), naive_up_bilinear(x))
    up = upsample2x(x, "nearest")
    for y in range(12):
        for xx in range(10):
            torch.testing.assert_close(up[..., y, xx], x[..., y // 2, xx // 2])


def test_down_of_nearest_up_is_identity():
    x = rand(2, 3, 6, 5, seed=3)
    torch.testing.assert_close(downsample2x(upsample2x(x, "nearest")), x, atol=0, rtol=0)


def test_bilinear_up_preserves_the_mean_away_from_borders_and_constants():
    c = torch.full((1, 2, 5, 4), 1.25, dtype=torch.float64)
    torch.testing.assert_close(upsample2x(c, "bilinear"), torch.full((1, 2, 10, 8), 1.25, dtype=torch.float64))
    # linear ramp in x: interior fine centres are sampled exactly on the ramp
    ramp = torch.arange(6, dtype=torch.float64).view(1, 1, 1, 6).expand(1, 1, 3, 6)
    up = upsample2x(ramp, "bilinear")
    fine_centres = (torch.arange(12, dtype=torch.float64) + 0.5) / 2 - 0.5
    torch.testing.assert_close(up[0, 0, 1, 1:-1], fine_centres[1:-1])


def test_odd_sizes_round_trip_with_size_crop():
    x = rand(1, 3, 11, 9, seed=4)
    pyr = build_pyramid(x, 3)
    assert [tuple(p.shape[-2:]) for p in pyr] == [(11, 9), (6, 5), (3, 3)]
    up = upsample2x(pyr[1], "nearest", size=(11, 9))
    assert up.shape == x.shape
    # the cropped last row/column is replicated back by downsample2x, giving the same coarse image
    torch.testing.assert_close(downsample2x(up), pyr[1])
    with pytest.raises(ValueError, match="size"):
        upsample2x(pyr[1], size=(9, 9))


def test_build_pyramid_levels():
    x = rand(1, 3, 12, 8, seed=5)
    pyr = build_pyramid(x, 3)
    assert pyr[0] is x and [p.shape[-1] for p in pyr] == [8, 4, 2]
    torch.testing.assert_close(pyr[2], x.view(1, 3, 3, 4, 2, 4).mean(dim=(3, 5)))
    with pytest.raises(ValueError):
        build_pyramid(x, 0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("factor", [1, 2, 3])
def test_block_mean_is_the_pooling_to_the_bit(factor, dtype):
    x = torch.rand(2, 5, 6 * factor, 4 * factor, generator=torch.Generator().manual_seed(factor), dtype=dtype) * 100
    assert torch.equal(block_mean(x, factor), F.avg_pool2d(x, factor))


def test_block_mean_of_a_known_block_and_other_dtypes():
    x = torch.tensor([[[[1.0, 2.0, 5.0, 9.0], [3.0, 6.0, 0.0, 2.0]]]])
    assert torch.equal(block_mean(x, 2), torch.tensor([[[[3.0, 4.0]]]]))
    half = x.to(torch.bfloat16)  # other dtypes keep the pooling (it accumulates them in float)
    assert torch.equal(block_mean(half, 2), F.avg_pool2d(half, 2))


def test_block_mean_refuses_partial_blocks_and_bad_factors():
    with pytest.raises(ValueError, match="a 5x4 image is not made of whole 2x2 blocks"):
        block_mean(torch.zeros(1, 1, 5, 4), 2)
    with pytest.raises(ValueError, match="factor must be a whole number >= 1, got 0"):
        block_mean(torch.zeros(1, 1, 4, 4), 0)
