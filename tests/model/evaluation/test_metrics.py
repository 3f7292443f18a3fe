"""Benchmark metrics: closed-form answers on tiny seeded images, and the protocol's encodings."""

from __future__ import annotations

import math
import sys

import pytest
import torch

from model.evaluation.metrics import (
    PSNR_CAP_DB,
    FovVideoVdp,
    flip,
    frame_metrics,
    psnr,
    smape,
    ssim,
    temporal_error,
)


def ldr(seed: int = 0, n: int = 1, h: int = 16, w: int = 16) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, h, w, generator=g)


def noisy(x: torch.Tensor, sigma: float, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (x + sigma * torch.randn(x.shape, generator=g)).clamp(0, 1)


def test_psnr_of_identical_images_is_the_cap():
    x = ldr()
    assert psnr(x, x).item() == pytest.approx(PSNR_CAP_DB)


def test_psnr_of_a_known_mse():
    a, b = torch.full((2, 3, 4, 5), 0.5), torch.full((2, 3, 4, 5), 0.6)  # MSE 0.01 -> 20 dB
    torch.testing.assert_close(psnr(a, b), torch.tensor([20.0, 20.0]), rtol=0, atol=1e-4)
    assert psnr(a, b, peak=2.0)[0].item() == pytest.approx(10 * math.log10(4 / 0.01), abs=1e-4)


def test_ssim_of_identical_images_is_one_and_drops_with_noise():
    x = ldr(n=2)
    torch.testing.assert_close(ssim(x, x), torch.ones(2), rtol=0, atol=1e-6)
    light, heavy = ssim(noisy(x, 0.05), x), ssim(noisy(x, 0.2), x)
    assert (light < 0.999).all() and (heavy < light).all()


def test_ssim_of_constant_images_has_the_closed_form():
    # No variance, no covariance: SSIM = (2 a b + C1) / (a^2 + b^2 + C1).
    a, b = 0.3, 0.7
    c1 = 0.01 ** 2
    expected = (2 * a * b + c1) / (a * a + b * b + c1)
    value = ssim(torch.full((1, 3, 12, 13), a), torch.full((1, 3, 12, 13), b))
    assert value.item() == pytest.approx(expected, rel=1e-6)


def test_ssim_matches_a_naive_gaussian_window_sum():
    # An 11x11 image has exactly one full window: SSIM is the formula on Gaussian-weighted statistics.
    a, b = ldr(3, h=11, w=11).double(), noisy(ldr(3, h=11, w=11), 0.1).double()
    coordinates = torch.arange(11, dtype=torch.float64) - 5
    g1 = torch.exp(-coordinates ** 2 / (2 * 1.5 ** 2))
    weights = g1[:, None] * g1[None, :]
    weights /= weights.sum()
    values = []
    for channel in range(3):
        x, y = a[0, channel], b[0, channel]
        mx, my = (weights * x).sum(), (weights * y).sum()
        vx, vy = (weights * x * x).sum() - mx ** 2, (weights * y * y).sum() - my ** 2
        cov = (weights * x * y).sum() - mx * my
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        values.append(((2 * mx * my + c1) * (2 * cov + c2)) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2)))
    assert ssim(a, b).item() == pytest.approx(float(sum(values) / 3), abs=1e-6)


def test_ssim_refuses_images_smaller_than_its_window():
    with pytest.raises(ValueError, match="11x11"):
        ssim(ldr(h=8, w=8), ldr(h=8, w=8))


def test_smape_closed_form():
    a, b = torch.full((1, 3, 2, 2), 1.0), torch.full((1, 3, 2, 2), 3.0)
    assert smape(a, b).item() == pytest.approx(2.0 / 4.01, rel=1e-6)
    assert smape(b, a).item() == pytest.approx(2.0 / 4.01, rel=1e-6)  # symmetric
    zeros = torch.zeros(1, 3, 2, 2)
    assert smape(zeros, zeros).item() == 0.0


def test_temporal_error_ignores_a_constant_offset_and_measures_flicker():
    g = torch.Generator().manual_seed(4)
    references = torch.rand(5, 3, 6, 7, generator=g)
    assert temporal_error(references + 0.25, references) == pytest.approx(0.0, abs=1e-6)  # float32 rounding

    # Output flickers by +-1 around a static reference: every change is 1.
    still = torch.zeros(4, 3, 2, 2)
    flicker = torch.tensor([0.0, 1.0, 0.0, 1.0]).view(4, 1, 1, 1).expand(4, 3, 2, 2)
    assert temporal_error(flicker, still) == pytest.approx(1.0)
    # A cut before frame 1 removes the pair (0, 1), the rest still flicker.
    assert temporal_error(flicker, still, camera_cuts=[False, True, False, False]) == pytest.approx(1.0)
    # A still output against a reference that changes only across the cut: zero error.
    step = torch.tensor([0.0, 0.0, 1.0, 1.0]).view(4, 1, 1, 1).expand(4, 3, 2, 2)
    assert temporal_error(still, step) == pytest.approx(1.0 / 3.0)
    assert temporal_error(still, step, camera_cuts=[False, False, True, False]) == pytest.approx(0.0)


def test_temporal_error_needs_a_pair_of_frames():
    one = torch.zeros(1, 3, 2, 2)
    assert temporal_error(one, one) is None
    with pytest.raises(ValueError, match="camera_cuts"):
        temporal_error(torch.zeros(3, 3, 2, 2), torch.zeros(3, 3, 2, 2), camera_cuts=[False])


def test_flip_is_zero_for_identical_images_and_grows_with_the_difference():
    x = ldr(5, n=2)
    torch.testing.assert_close(flip(x, x), torch.zeros(2), rtol=0, atol=1e-7)
    light, heavy = flip(noisy(x, 0.05), x), flip(noisy(x, 0.3), x)
    assert (light > 0).all() and (heavy > light).all()


def test_flip_refuses_values_outside_the_ldr_range():
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        flip(ldr() * 2, ldr())


def test_frame_metrics_encode_hdr_for_display():
    reference = ldr(6, n=2) * 4  # HDR: most of it clips to white on the display
    output = reference * 1.5  # brighter, but where both clip the display images agree
    metrics = frame_metrics(output, reference)
    assert set(metrics) == {"psnr", "ssim", "flip", "smape"}
    assert all(values.shape == (2,) and torch.isfinite(values).all() for values in metrics.values())
    expected_smape = (0.5 * reference[0] / (2.5 * reference[0] + 0.01)).mean().item()  # on linear HDR
    assert metrics["smape"][0].item() == pytest.approx(expected_smape, rel=1e-5)
    # PSNR is taken on clip(x, 0, 1) ** (1/2.2): pixels where both clip to white do not count as errors.
    encoded = psnr(output.clamp(0, 1) ** (1 / 2.2), reference.clamp(0, 1) ** (1 / 2.2))
    torch.testing.assert_close(metrics["psnr"], encoded, rtol=0, atol=1e-4)
    assert (metrics["psnr"] > psnr(output, reference) + 10).all()


def test_fovvideovdp_gives_ten_jod_for_identical_videos_and_less_for_noise():
    metric = FovVideoVdp()
    assert metric.available, metric.unavailable_reason
    reference = ldr(7, n=3)
    assert metric.jod(reference, reference) == pytest.approx(10.0, abs=1e-3)
    assert metric.jod(noisy(reference, 0.2), reference) < 9.5


def test_fovvideovdp_reports_why_it_is_unavailable(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyfvvdp", None)  # import fails as if the package were missing
    metric = FovVideoVdp()
    assert not metric.available
    assert "pyfvvdp" in metric.unavailable_reason
    with pytest.raises(RuntimeError, match="pyfvvdp"):
        metric.jod(ldr(), ldr())
