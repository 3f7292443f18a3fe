"""box_mean / replicated_box_mean against a per-pixel loop and against the average pooling they replace (box_sum:
test_splat)."""

import pytest
import torch
import torch.nn.functional as F

from model.ops.box_filter import box_mean, replicated_box_extremes, replicated_box_mean


def naive_box_mean(image, size, replicate):
    n, c, h, w = image.shape
    out = torch.zeros_like(image)
    for y in range(h):
        for x in range(w):
            rows = range(y - size // 2, y + size // 2 + 1)
            cols = range(x - size // 2, x + size // 2 + 1)
            if replicate:
                taps = [image[:, :, min(max(r, 0), h - 1), min(max(q, 0), w - 1)] for r in rows for q in cols]
            else:
                taps = [image[:, :, r, q] for r in rows for q in cols if 0 <= r < h and 0 <= q < w]
            out[:, :, y, x] = torch.stack(taps).mean(dim=0)
    return out


@pytest.mark.parametrize("size", [1, 3, 5, 13])  # 13: wider than the image
def test_box_mean_is_the_mean_of_the_window_inside_the_image(size):
    image = torch.rand(2, 3, 7, 9, generator=torch.Generator().manual_seed(size), dtype=torch.float64)
    torch.testing.assert_close(box_mean(image, size), naive_box_mean(image, size, False))


@pytest.mark.parametrize("size", [1, 3, 5])
def test_replicated_box_mean_repeats_the_edge(size):
    image = torch.rand(1, 2, 6, 5, generator=torch.Generator().manual_seed(size), dtype=torch.float64)
    torch.testing.assert_close(replicated_box_mean(image, size), naive_box_mean(image, size, True))


@pytest.mark.parametrize("size", [9, 33])
def test_they_equal_the_average_pooling_they_replace(size):
    image = torch.rand(1, 3, 40, 36, generator=torch.Generator().manual_seed(size))
    radius = size // 2
    pooled = F.avg_pool2d(image, size, stride=1, padding=radius, count_include_pad=False)
    torch.testing.assert_close(box_mean(image, size), pooled)
    replicated = F.avg_pool2d(F.pad(image, (radius,) * 4, mode="replicate"), size, stride=1)
    torch.testing.assert_close(replicated_box_mean(image, size), replicated)


@pytest.mark.parametrize("size", [1, 3, 5])
def test_replicated_box_extremes_are_the_window_max_and_min(size):
    image = torch.rand(2, 2, 6, 5, generator=torch.Generator().manual_seed(size + 7), dtype=torch.float64)
    high, low = replicated_box_extremes(image, size)
    h, w = image.shape[-2:]
    r = size // 2
    for y in range(h):
        for x in range(w):
            taps = torch.stack([image[:, :, min(max(q, 0), h - 1), min(max(p, 0), w - 1)]
                                for q in range(y - r, y + r + 1) for p in range(x - r, x + r + 1)])
            assert torch.equal(high[:, :, y, x], taps.amax(dim=0)) and torch.equal(low[:, :, y, x], taps.amin(dim=0))


def test_an_even_or_empty_window_is_refused_with_its_size():
    with pytest.raises(ValueError, match="k must be a positive odd integer, got 4"):
        box_mean(torch.zeros(1, 1, 4, 4), 4)
    with pytest.raises(ValueError, match="k must be a positive odd integer, got 0"):
        replicated_box_mean(torch.zeros(1, 1, 4, 4), 0)
    with pytest.raises(ValueError, match="k must be a positive odd integer, got 2"):
        replicated_box_extremes(torch.zeros(1, 1, 4, 4), 2)
    with pytest.raises(ValueError, match=r"\(N, C, H, W\)"):
        box_mean(torch.zeros(4, 4), 3)


def test_box_mean_passes_gradients_through_its_sums():
    image = torch.rand(1, 1, 5, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda t: box_mean(t, 3), (image,))
    assert torch.autograd.gradcheck(lambda t: replicated_box_mean(t, 3), (image,))
