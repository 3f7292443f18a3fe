"""apply_pixel_kernels against a per-pixel loop, an unfold formulation, and closed forms."""

import math

import pytest
import torch
import torch.nn.functional as F

from model.ops.kernels import apply_pixel_kernels, kernel_offsets
from tests.builders import rand


def naive_apply(image, kernels, k, dilation, normalize):
    n_, c_, h, w = image.shape
    r = k // 2
    out = torch.zeros_like(image)
    for n in range(n_):
        for y in range(h):
            for x in range(w):
                taps = []  # (weight, y, x) of the in-image taps, row-major order
                for ky in range(k):
                    for kx in range(k):
                        yy, xx = y + (ky - r) * dilation, x + (kx - r) * dilation
                        if 0 <= yy < h and 0 <= xx < w:
                            taps.append((kernels[n, ky * k + kx, y, x].item(), yy, xx))
                if normalize == "softmax":
                    mx = max(t[0] for t in taps)
                    ws = [math.exp(t[0] - mx) for t in taps]
                else:
                    ws = [t[0] for t in taps]
                # normalization runs over the in-image taps only; "none" keeps the raw weights
                total = sum(ws) if normalize != "none" else 1.0
                for c in range(c_):
                    out[n, c, y, x] = sum(wj * image[n, c, yy, xx].item() for wj, (_, yy, xx) in zip(ws, taps)) / total
    return out


@pytest.mark.parametrize("normalize", ["none", "softmax", "sum"])
@pytest.mark.parametrize("k,dilation", [(3, 1), (5, 1), (3, 2)])
def test_matches_naive(k, dilation, normalize):
    image = rand(2, 3, 12, 10, seed=1, lo=-1, hi=2)
    lo = -3.0 if normalize == "softmax" else (0.05 if normalize == "sum" else -1.0)
    kernels = rand(2, k * k, 12, 10, seed=2, lo=lo, hi=3.0)
    got = apply_pixel_kernels(image, kernels, k, dilation=dilation, normalize=normalize)
    torch.testing.assert_close(got, naive_apply(image, kernels, k, dilation, normalize))


def test_matches_unfold_formulation():
    # The memory-hungry formulation the loop replaces: F.unfold (zero padding) times the kernel map.
    image = rand(1, 3, 12, 10, seed=3)
    kernels = rand(1, 25, 12, 10, seed=4, lo=-1)
    unfolded = F.unfold(image, 5, padding=2).view(1, 3, 25, 12, 10)
    ref = (unfolded * kernels.unsqueeze(1)).sum(dim=2)
    torch.testing.assert_close(apply_pixel_kernels(image, kernels, 5), ref)


def test_one_hot_kernel_is_a_shift_with_zero_padding():
    image = rand(1, 3, 12, 10, seed=5)
    k = 5
    offsets = kernel_offsets(k)
    j = offsets.index((2, -1))  # read 2 px right, 1 px up
    kernels = torch.zeros(1, k * k, 12, 10, dtype=torch.float64)
    kernels[:, j] = 1.0
    out = apply_pixel_kernels(image, kernels, k)
    expected = torch.zeros_like(image)
    expected[..., 1:, :-2] = image[..., :-1, 2:]
    torch.testing.assert_close(out, expected, atol=0, rtol=0)


@pytest.mark.parametrize("normalize", ["softmax", "sum"])
def test_normalized_kernels_keep_a_constant_image_constant_up_to_the_border(normalize):
    image = torch.full((1, 3, 12, 10), 0.37, dtype=torch.float64)
    kernels = rand(1, 49, 12, 10, seed=6, lo=0.1, hi=4)
    out = apply_pixel_kernels(image, kernels, 7, dilation=2, normalize=normalize)
    torch.testing.assert_close(out, image)


def test_softmax_does_not_underflow_when_the_max_tap_is_outside():
    # Logit 1000 on a tap outside the image: a max taken over all taps would underflow every real tap.
    image = rand(1, 1, 4, 4, seed=7)
    kernels = torch.zeros(1, 9, 4, 4, dtype=torch.float32)
    kernels[:, 0] = 1000.0  # top-left tap: outside for row 0 / column 0
    out = apply_pixel_kernels(image.float(), kernels, 3, normalize="softmax")
    assert bool(torch.isfinite(out).all())


def test_hand_written_backward_matches_finite_differences():
    image = rand(1, 2, 5, 4, seed=8).requires_grad_()
    kernels = rand(1, 9, 5, 4, seed=9, lo=-1).requires_grad_()
    # fast_mode compares a random projection of the analytical Jacobian (the hand-written backward) with finite
    # differences, which is enough to catch a wrong tap or sign and keeps the test fast.
    assert torch.autograd.gradcheck(
        lambda i, kk: apply_pixel_kernels(i, kk, 3, dilation=2), (image, kernels), fast_mode=True
    )
    assert torch.autograd.gradcheck(
        lambda i, kk: apply_pixel_kernels(i, kk, 3, normalize="softmax"), (image, kernels), fast_mode=True
    )
    # only one input requiring grad
    image2 = image.detach().requires_grad_()
    apply_pixel_kernels(image2, kernels.detach(), 3).sum().backward()
    assert image2.grad is not None


def test_rejects_wrong_kernel_shape():
    with pytest.raises(ValueError, match="kernels"):
        apply_pixel_kernels(torch.zeros(1, 3, 4, 4), torch.zeros(1, 9, 4, 4), 5)
    with pytest.raises(ValueError, match="normalize"):
        apply_pixel_kernels(torch.zeros(1, 3, 4, 4), torch.zeros(1, 9, 4, 4), 3, normalize="l1")


def test_kernels_in_channels_last_give_the_same_output():
    # a channels_last network hands over strided kernels; they are read as a contiguous copy
    image, logits = rand(1, 3, 9, 7, seed=3), rand(1, 9, 9, 7, seed=4) * 3
    strided = logits.contiguous(memory_format=torch.channels_last)
    assert not strided.is_contiguous()
    torch.testing.assert_close(apply_pixel_kernels(image, strided, 3, normalize="softmax"),
                               apply_pixel_kernels(image, logits, 3, normalize="softmax"))
