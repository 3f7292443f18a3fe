"""WSKPN weight-sharing filter against a per-pixel loop, the paper's unfold + softmax form, and closed forms."""

import pytest
import torch

from model.ops.kernels import apply_pixel_kernels
from model.ops.splat import box_sum, fuse_kernel_sizes, weight_sharing_filter, weight_sharing_fused
from tests.builders import rand


def naive_ws(image, weight, k):
    n_, c_, h, w = image.shape
    r = k // 2
    out = torch.zeros_like(image)
    for n in range(n_):
        for y in range(h):
            for x in range(w):
                for c in range(c_):
                    wc = weight.shape[1] > 1
                    num = den = 0.0
                    for yy in range(max(0, y - r), min(h, y + r + 1)):
                        for xx in range(max(0, x - r), min(w, x + r + 1)):
                            wq = weight[n, c if wc else 0, yy, xx].item()
                            num += wq * image[n, c, yy, xx].item()
                            den += wq
                    out[n, c, y, x] = num / den
    return out


@pytest.mark.parametrize("k", [3, 5, 13])
def test_matches_naive(k):
    image = rand(2, 3, 12, 10, seed=1, hi=5)
    weight = rand(2, 1, 12, 10, seed=2, lo=0.01, hi=3)
    torch.testing.assert_close(weight_sharing_filter(image, weight, k), naive_ws(image, weight, k))


def test_per_channel_importance_and_logits():
    image = rand(1, 3, 12, 10, seed=3)
    logits = rand(1, 3, 12, 10, seed=4, lo=-4, hi=4)
    ref = naive_ws(image, logits.exp(), 5)
    torch.testing.assert_close(weight_sharing_filter(image, logits, 5, from_logits=True), ref)
    torch.testing.assert_close(weight_sharing_filter(image, logits.exp(), 5), ref)


def test_equals_papers_unfolded_softmax_kernels():
    # Paper eq. 3: kernel of p = softmax over window(p) of the importance logits, built by unfold (here as an
    # explicit k*k map and applied by apply_pixel_kernels, whose softmax also skips out-of-image taps).
    image = rand(1, 3, 12, 10, seed=5)
    logits = rand(1, 1, 12, 10, seed=6, lo=-3, hi=3)
    k, r = 7, 3
    padded = torch.nn.functional.pad(logits, (r, r, r, r))
    kernel_map = torch.cat([padded[..., ky : ky + 12, kx : kx + 10] for ky in range(k) for kx in range(k)], dim=1)
    ref = apply_pixel_kernels(image, kernel_map, k, normalize="softmax")
    torch.testing.assert_close(weight_sharing_filter(image, logits, k, from_logits=True), ref)


def test_constant_image_stays_constant():
    image = torch.full((2, 3, 12, 10), 2.5, dtype=torch.float64)
    weight = rand(2, 1, 12, 10, seed=7, lo=1e-3, hi=10)
    for k in (3, 7, 13):
        torch.testing.assert_close(weight_sharing_filter(image, weight, k), image)


def test_delta_importance_spreads_that_pixel():
    image = rand(1, 3, 12, 10, seed=8)
    weight = torch.full((1, 1, 12, 10), 1e-20, dtype=torch.float64)
    qy, qx, k = 5, 4, 5
    weight[..., qy, qx] = 1.0
    out = weight_sharing_filter(image, weight, k)
    r = k // 2
    for y in range(12):
        for x in range(10):
            if abs(y - qy) <= r and abs(x - qx) <= r:  # q in window(p): p takes q's colour
                torch.testing.assert_close(out[..., y, x], image[..., qy, qx], atol=1e-15, rtol=1e-15)
            else:  # uniform weights elsewhere: plain box mean of the (clipped) window
                ys, xs = slice(max(0, y - r), y + r + 1), slice(max(0, x - r), x + r + 1)
                torch.testing.assert_close(out[..., y, x], image[..., ys, xs].mean(dim=(-2, -1)))


def test_box_sum_naive_and_gradient():
    x = rand(1, 2, 12, 10, seed=9)
    got = box_sum(x, 5)
    ref = torch.zeros_like(x)
    for y in range(12):
        for xx in range(10):
            ref[..., y, xx] = x[..., max(0, y - 2) : y + 3, max(0, xx - 2) : xx + 3].sum(dim=(-2, -1))
    torch.testing.assert_close(got, ref)
    assert torch.autograd.gradcheck(lambda t: box_sum(t, 3), (rand(1, 1, 5, 4, seed=10).requires_grad_(),))


def test_filter_gradcheck():
    image = rand(1, 2, 5, 4, seed=11).requires_grad_()
    logits = rand(1, 1, 5, 4, seed=12, lo=-2, hi=2).requires_grad_()
    assert torch.autograd.gradcheck(
        lambda i, l: weight_sharing_filter(i, l, 3, from_logits=True), (image, logits)
    )


def test_extreme_logits_stay_finite():
    image = rand(1, 3, 12, 10, seed=13).float()
    logits = torch.zeros(1, 1, 12, 10)
    logits[..., 0, 0] = 500.0  # would overflow exp() without the shift
    logits[..., 11, 9] = -500.0  # would underflow every weight around it without the clamp
    out = weight_sharing_filter(image, logits, 3, from_logits=True)
    assert bool(torch.isfinite(out).all())
    torch.testing.assert_close(out[..., 1, 1], image[..., 0, 0])


def test_fuse_kernel_sizes_and_full_pipeline():
    image = rand(2, 3, 12, 10, seed=14)
    sizes = (3, 5, 9)
    imp = rand(2, 3, 12, 10, seed=15, lo=-2, hi=2)
    fusion = rand(2, 3, 12, 10, seed=16, lo=-2, hi=2)
    outs = [naive_ws(image, imp[:, i : i + 1].exp(), k) for i, k in enumerate(sizes)]
    fused = fuse_kernel_sizes(outs, fusion)
    ref = torch.zeros_like(image)
    for n in range(2):
        for y in range(12):
            for x in range(10):
                e = fusion[n, :, y, x].exp()
                a = e / e.sum()
                ref[n, :, y, x] = sum(a[i] * outs[i][n, :, y, x] for i in range(3))
    torch.testing.assert_close(fused, ref)
    torch.testing.assert_close(weight_sharing_fused(image, imp, fusion, sizes), ref)
    with pytest.raises(ValueError, match="fusion_logits"):
        fuse_kernel_sizes(outs, fusion[:, :2])
