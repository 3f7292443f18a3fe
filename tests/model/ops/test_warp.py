"""backward_warp / upscale_motion / dilate_motion_by_depth against per-pixel loops and closed forms."""

import math

import pytest
import torch

from model.ops.warp import backward_warp, bilinear_spread, dilate_motion_by_depth, upscale_motion
from tests.builders import rand

A = -0.75  # torch's bicubic coefficient


def _tap(img, n, c, x, y, padding):
    h, w = img.shape[-2:]
    if padding == "border":
        return img[n, c, min(max(y, 0), h - 1), min(max(x, 0), w - 1)].item()
    if 0 <= x < w and 0 <= y < h:
        return img[n, c, y, x].item()
    return 0.0


def _cubic_weights(t):
    def near(d):  # |d| <= 1
        return ((A + 2) * d - (A + 3)) * d * d + 1

    def far(d):  # 1 < |d| < 2
        return ((A * d - 5 * A) * d + 8 * A) * d - 4 * A

    return [far(t + 1), near(t), near(1 - t), far(2 - t)]


def naive_warp(prev, motion, mode, padding):
    n_, c_, h, w = prev.shape
    out = torch.zeros_like(prev)
    inside = torch.zeros(n_, 1, h, w, dtype=torch.bool)
    for n in range(n_):
        for y in range(h):
            for x in range(w):
                px = x + 0.5 + motion[n, 0, y, x].item()
                py = y + 0.5 + motion[n, 1, y, x].item()
                inside[n, 0, y, x] = 0 <= px < w and 0 <= py < h
                # continuous position -> index space where pixel i's centre is i
                u, v = px - 0.5, py - 0.5
                for c in range(c_):
                    if mode == "nearest":
                        ix, iy = math.floor(px), math.floor(py)
                        if padding == "zeros" and not inside[n, 0, y, x]:
                            val = 0.0
                        else:
                            val = _tap(prev, n, c, ix, iy, "border")
                    elif mode == "bilinear":
                        x0, y0 = math.floor(u), math.floor(v)
                        tx, ty = u - x0, v - y0
                        val = 0.0
                        for dy, wy in ((0, 1 - ty), (1, ty)):
                            for dx, wx in ((0, 1 - tx), (1, tx)):
                                val += wx * wy * _tap(prev, n, c, x0 + dx, y0 + dy, padding)
                    else:
                        x0, y0 = math.floor(u), math.floor(v)
                        wxs, wys = _cubic_weights(u - x0), _cubic_weights(v - y0)
                        val = 0.0
                        for j in range(4):
                            for i in range(4):
                                val += wxs[i] * wys[j] * _tap(prev, n, c, x0 - 1 + i, y0 - 1 + j, padding)
                    out[n, c, y, x] = val
    return out, inside


@pytest.mark.parametrize("mode", ["bilinear", "bicubic", "nearest"])
@pytest.mark.parametrize("padding", ["border", "zeros"])
def test_backward_warp_matches_naive(mode, padding):
    prev = rand(2, 3, 12, 10, seed=1)
    motion = rand(2, 2, 12, 10, seed=2, lo=-3.0, hi=3.0)
    warped, inside = backward_warp(prev, motion, mode=mode, padding=padding)
    ref, ref_inside = naive_warp(prev, motion, mode, padding)
    assert inside.dtype == torch.bool and inside.shape == (2, 1, 12, 10)
    assert torch.equal(inside, ref_inside)
    torch.testing.assert_close(warped, ref, atol=1e-9, rtol=0)


def test_nearest_uses_pixel_footprint_on_half_pixel_motion():
    # motion 0.5 puts the sample exactly on the boundary x = i + 1, which belongs to pixel i + 1 ([x, x+1)).
    prev = torch.arange(10, dtype=torch.float32).view(1, 1, 1, 10).expand(1, 1, 3, 10).contiguous()
    motion = torch.zeros(1, 2, 3, 10)
    motion[:, 0] = 0.5
    warped, inside = backward_warp(prev, motion, mode="nearest")
    torch.testing.assert_close(warped[0, 0, 0, :-1], prev[0, 0, 0, 1:], atol=0, rtol=0)
    assert bool(inside[..., :-1].all()) and not bool(inside[..., -1].any())


# float64: exact to rounding. float32: grid_sample's normalized coordinates go through a few float32 operations
# inside torch, which leaves ~1e-7 px of position error on small images (bicubic amplifies it a little).
TOL = {torch.float64: 1e-12, torch.float32: 4e-6}


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("mode", ["bilinear", "bicubic", "nearest"])
def test_integer_motion_is_an_exact_shift(mode, dtype):
    tol = TOL[dtype]
    prev = rand(1, 3, 12, 10, seed=3, dtype=dtype)
    motion = torch.zeros(1, 2, 12, 10, dtype=dtype)
    motion[:, 0] = 1.0  # read one pixel to the right
    warped, inside = backward_warp(prev, motion, mode=mode, padding="border")
    torch.testing.assert_close(warped[..., :, :-1], prev[..., :, 1:], atol=tol, rtol=0)
    torch.testing.assert_close(warped[..., :, -1], prev[..., :, -1], atol=tol, rtol=0)  # border
    assert bool(inside[..., :-1].all()) and not bool(inside[..., -1].any())

    motion = torch.zeros(1, 2, 12, 10, dtype=dtype)
    motion[:, 1] = -2.0  # read two pixels up
    warped, inside = backward_warp(prev, motion, mode=mode, padding="zeros")
    torch.testing.assert_close(warped[..., 2:, :], prev[..., :-2, :], atol=tol, rtol=0)
    torch.testing.assert_close(warped[..., :2, :], torch.zeros_like(warped[..., :2, :]), atol=tol, rtol=0)
    assert not bool(inside[..., :2, :].any()) and bool(inside[..., 2:, :].all())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_zero_motion_is_identity(dtype):
    prev = rand(1, 3, 12, 10, seed=4, dtype=dtype)
    for mode in ("bilinear", "bicubic", "nearest"):
        warped, inside = backward_warp(prev, torch.zeros(1, 2, 12, 10, dtype=dtype), mode=mode)
        torch.testing.assert_close(warped, prev, atol=TOL[dtype], rtol=0)
        assert bool(inside.all())


def test_bilinear_half_pixel_is_mean_of_neighbours():
    prev = rand(1, 1, 4, 6, seed=5)
    motion = torch.zeros(1, 2, 4, 6, dtype=torch.float64)
    motion[:, 0] = 0.5
    warped, _ = backward_warp(prev, motion)
    torch.testing.assert_close(warped[..., :-1], 0.5 * (prev[..., :-1] + prev[..., 1:]))


def test_warp_is_differentiable_in_prev_and_motion():
    prev = rand(1, 2, 4, 5, seed=6).requires_grad_()
    motion = rand(1, 2, 4, 5, seed=7, lo=-0.8, hi=0.8).requires_grad_()
    assert torch.autograd.gradcheck(lambda p, m: backward_warp(p, m)[0], (prev, motion))


def test_warp_rejects_bad_arguments():
    prev = torch.zeros(1, 3, 4, 4)
    with pytest.raises(ValueError, match="motion"):
        backward_warp(prev, torch.zeros(1, 2, 4, 5))
    with pytest.raises(ValueError, match="mode"):
        backward_warp(prev, torch.zeros(1, 2, 4, 4), mode="lanczos")
    with pytest.raises(ValueError, match="padding"):
        backward_warp(prev, torch.zeros(1, 2, 4, 4), padding="reflection")


def test_upscale_motion_nearest_integer_scale():
    motion = rand(2, 2, 6, 5, seed=8, lo=-2, hi=2)
    up = upscale_motion(motion, 2, mode="nearest")
    assert up.shape == (2, 2, 12, 10)
    for y in range(12):
        for x in range(10):
            torch.testing.assert_close(up[:, :, y, x], 2 * motion[:, :, y // 2, x // 2])


def test_upscale_motion_bilinear_constant_and_fractional_scale():
    motion = torch.empty(1, 2, 6, 4, dtype=torch.float64)
    motion[:, 0], motion[:, 1] = 1.5, -0.25
    up = upscale_motion(motion, 1.5, mode="bilinear")
    assert up.shape == (1, 2, 9, 6)
    torch.testing.assert_close(up[:, 0], torch.full((1, 9, 6), 2.25, dtype=torch.float64))
    torch.testing.assert_close(up[:, 1], torch.full((1, 9, 6), -0.375, dtype=torch.float64))


def naive_dilate(motion, depth, k):
    out = motion.clone()
    n_, _, h, w = depth.shape
    r = k // 2
    for n in range(n_):
        for y in range(h):
            for x in range(w):
                best = depth[n, 0, y, x].item() if depth[n, 0, y, x] > 0 else math.inf
                by, bx = y, x
                for dy in range(-r, r + 1):
                    for dx in range(-r, r + 1):
                        yy, xx = y + dy, x + dx
                        if 0 <= yy < h and 0 <= xx < w and depth[n, 0, yy, xx] > 0 and depth[n, 0, yy, xx] < best:
                            best, by, bx = depth[n, 0, yy, xx].item(), yy, xx
                out[n, :, y, x] = motion[n, :, by, bx]
    return out


@pytest.mark.parametrize("k", [3, 5])
def test_dilate_motion_matches_naive(k):
    motion = rand(2, 2, 12, 10, seed=9, lo=-4, hi=4)
    depth = rand(2, 1, 12, 10, seed=10, lo=0.5, hi=10)
    depth[rand(2, 1, 12, 10, seed=11) < 0.3] = 0.0  # some "no surface" pixels
    torch.testing.assert_close(dilate_motion_by_depth(motion, depth, k), naive_dilate(motion, depth, k))


def test_dilate_motion_grows_foreground_by_radius():
    depth = torch.full((1, 1, 12, 10), 5.0)
    depth[..., 4:7, 3:6] = 1.0  # near object
    depth[..., 0, :] = 0.0  # a row with no surface
    motion = torch.zeros(1, 2, 12, 10)
    motion[:, 0, 4:7, 3:6] = 3.0
    motion[:, 1, 0, :] = 7.0  # motion of "no surface" pixels must never spread
    out = dilate_motion_by_depth(motion, depth, k=3)
    # The object's motion spreads one pixel out; row 0 has no surface, so it takes row 1's (background) motion 0.
    expected = torch.zeros(1, 2, 12, 10)
    expected[:, 0, 3:8, 2:7] = 3.0
    torch.testing.assert_close(out, expected)

    empty = torch.zeros(1, 1, 12, 10)
    torch.testing.assert_close(dilate_motion_by_depth(motion, empty, k=3), motion)


def test_jitter_adds_to_the_read_position():
    prev = rand(2, 3, 12, 10, seed=12)
    motion = rand(2, 2, 12, 10, seed=13, lo=-2, hi=2)
    for mode in ("bilinear", "bicubic", "nearest"):
        shifted = motion.clone()
        shifted[:, 0] += 0.25
        shifted[:, 1] -= 0.5
        ref = backward_warp(prev, shifted, mode=mode)
        got = backward_warp(prev, motion, mode=mode, jitter=(0.25, -0.5))
        torch.testing.assert_close(got[0], ref[0])
        assert torch.equal(got[1], ref[1])
    # one jitter per sample
    per_sample = torch.tensor([[0.25, -0.5], [-0.125, 0.375]], dtype=torch.float64)
    got = backward_warp(prev, motion, jitter=per_sample)[0]
    for n in range(2):
        ref = backward_warp(prev[n : n + 1], motion[n : n + 1], jitter=per_sample[n].tolist())[0]
        torch.testing.assert_close(got[n : n + 1], ref)
    with pytest.raises(ValueError, match="jitter"):
        backward_warp(prev, motion, jitter=(0.1, 0.2, 0.3))


def test_bilinear_spread_is_the_variance_of_the_bilinear_reads_taps():
    # Read images of the pixels' coordinates and their squares: the bilinear read returns E[x] and E[x^2] over
    # its taps, so their variance is what the closed form claims (away from the border, where taps are clamped).
    torch.manual_seed(0)
    h = w = 12
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64),
                            indexing="ij")
    coords = torch.stack([xs, ys, xs**2, ys**2]).unsqueeze(0)
    motion = (torch.rand(1, 2, h, w, dtype=torch.float64) - 0.5) * 6
    read, _ = backward_warp(coords, motion, mode="bilinear")
    variance = (read[:, 2:4] - read[:, 0:2] ** 2).sum(dim=1, keepdim=True)
    inner = (slice(None), slice(None), slice(4, -4), slice(4, -4))
    torch.testing.assert_close(bilinear_spread(motion)[inner], 2 * variance[inner], atol=1e-9, rtol=0)


def test_bilinear_spread_is_zero_at_whole_pixels_and_one_at_half_pixels():
    motion = torch.tensor([[0.0, 0.5, -3.0, 0.5], [2.0, 0.5, 0.5, 0.0]]).reshape(1, 2, 1, 4)
    assert bilinear_spread(motion).flatten().tolist() == [0.0, 1.0, 0.5, 0.5]
    with pytest.raises(ValueError, match="motion must be"):
        bilinear_spread(torch.zeros(1, 3, 2, 2))


@pytest.mark.parametrize("mode", ["bilinear", "bicubic"])
@pytest.mark.parametrize("height", [16, 13])  # 13 rows do not split evenly in two: the last part is padded, cropped
def test_a_single_frame_split_over_threads_reads_what_one_call_reads(mode, height):
    generator = torch.Generator().manual_seed(height)
    prev = torch.rand(1, 5, height, 11, generator=generator)
    motion = (torch.rand(1, 2, height, 11, generator=generator) - 0.5) * 6
    previous_threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # one thread: one grid_sample call
        single, _ = backward_warp(prev, motion, mode=mode)
        torch.set_num_threads(2)  # two: two batch items of half the rows each
        split, _ = backward_warp(prev, motion, mode=mode)
    finally:
        torch.set_num_threads(previous_threads)
    assert torch.equal(split, single)


def test_the_split_warp_carries_the_same_gradients():
    # a training batch of one goes through the split too: its gradients must be the single call's
    generator = torch.Generator().manual_seed(5)
    prev = torch.rand(1, 3, 13, 9, generator=generator, dtype=torch.float64, requires_grad=True)
    motion = ((torch.rand(1, 2, 13, 9, generator=generator, dtype=torch.float64) - 0.5) * 4).requires_grad_()
    previous_threads, results = torch.get_num_threads(), []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            warped, _ = backward_warp(prev, motion, mode="bicubic")
            weights = torch.arange(warped.numel(), dtype=warped.dtype).view_as(warped)
            results.append((warped.detach(), *torch.autograd.grad((warped * weights).sum(), [prev, motion])))
    finally:
        torch.set_num_threads(previous_threads)
    for single, split in zip(*results):
        torch.testing.assert_close(split, single, rtol=0, atol=1e-12)
