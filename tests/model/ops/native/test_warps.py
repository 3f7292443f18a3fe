"""The native reprojection equals the torch warps and geometry test it replaces, on seeded frames."""

import pytest
import torch
import torch.nn.functional as F

from model.ops.native.warps import reproject_x1
from model.ops.reproject import disocclusion_mask
from model.ops.warp import backward_warp


def _case(seed: int, h: int = 37, w: int = 53):
    g = torch.Generator().manual_seed(seed)
    smooth = F.interpolate(torch.randn(1, 2, 4, 4, generator=g), size=(h, w), mode="bilinear")
    motion = torch.tensor([1.3, -0.7]).view(1, 2, 1, 1) + 4 * smooth
    motion[:, :, :5] = torch.round(motion[:, :, :5])  # whole pixels: taps exactly on pixels
    motion[:, 0, 6:8] = 0.5  # half-way reads
    motion[:, :, -4:] *= 20  # far outside the image: border padding, invalid
    # smooth surfaces, so a warped neighbour often passes the geometry test
    depth = F.interpolate(torch.rand(1, 1, 3, 3, generator=g), size=(h, w), mode="bilinear") + 0.5
    depth[:, :, :, :3] = 0  # no surface
    normal = F.normalize(F.interpolate(torch.randn(1, 3, 3, 3, generator=g), size=(h, w), mode="bilinear"), dim=1)
    prev_depth = depth * (1 + 0.1 * torch.randn(1, 1, h, w, generator=g))
    prev_normal = F.normalize(normal + 0.3 * torch.randn(1, 3, h, w, generator=g), dim=1)
    images = [torch.rand(1, c, h, w, generator=g) for c in (3, 3, 4, 1, 2)]
    return motion, depth, normal, prev_depth, prev_normal, images


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_equals_the_torch_warps_and_test(seed):
    motion, depth, normal, prev_depth, prev_normal, (a, b, c, d, e) = _case(seed)
    jitter = torch.tensor([[0.25, -0.375]])
    with torch.no_grad():
        cubic, linear, nearest, valid = reproject_x1(motion, [a, b], (0.0, 1.0 - 1e-4), [c, d], [e], depth, normal,
                                                     prev_depth, prev_normal, jitter, 0.1, 0.9)
        expected_cubic = backward_warp(torch.cat([a, b], 1), motion, mode="bicubic")[0].clamp(0.0, 1.0 - 1e-4)
        expected_linear = backward_warp(torch.cat([c, d], 1), motion, mode="bilinear")[0]
        expected_nearest = backward_warp(e, motion, mode="nearest")[0]
        expected_valid = disocclusion_mask(depth, normal, prev_depth, prev_normal, motion, 0.1, 0.9, jitter=jitter)
    torch.testing.assert_close(cubic, expected_cubic, atol=1e-5, rtol=0)
    torch.testing.assert_close(linear, expected_linear, atol=1e-5, rtol=0)
    assert torch.equal(nearest, expected_nearest)
    assert torch.equal(valid, expected_valid)
    assert 0.1 < valid.float().mean() < 0.9  # both answers occur


def test_without_cubic_or_linear_images():
    motion, depth, normal, prev_depth, prev_normal, images = _case(3)
    with torch.no_grad():
        cubic, linear, nearest, valid = reproject_x1(motion, [], (0.0, 1.0), [], [images[4]], depth, normal,
                                                     prev_depth, prev_normal, torch.zeros(1, 2), 0.1, 0.9)
    assert cubic.shape[1] == 0 and linear.shape[1] == 0
    assert torch.equal(nearest, backward_warp(images[4], motion, mode="nearest")[0])


def test_more_channels_than_one_vector_load_reads_are_refused():
    motion, depth, normal, prev_depth, prev_normal, images = _case(4)
    with pytest.raises(ValueError, match="at most 8 bicubic"):
        reproject_x1(motion, [images[0]] * 3, (0.0, 1.0), [], [], depth, normal, prev_depth, prev_normal,
                     torch.zeros(1, 2), 0.1, 0.9)
