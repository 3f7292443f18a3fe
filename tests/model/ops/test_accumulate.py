"""accumulate / accumulate_moments against per-pixel loops and the running-mean closed form."""

import pytest
import torch

from model.ops.accumulate import accumulate, accumulate_moments, update_count
from tests.builders import rand

LUMA = (0.2126, 0.7152, 0.0722)


def naive_accumulate(cur, hist, hcount, valid, alpha_min, max_count):
    out, cnt = torch.empty_like(cur), torch.empty_like(hcount)
    n_, c_, h, w = cur.shape
    for n in range(n_):
        for y in range(h):
            for x in range(w):
                if valid[n, 0, y, x]:
                    k = hcount[n, 0, y, x].item() + 1
                    if max_count is not None:
                        k = min(k, max_count)
                    a = max(1.0 / k, alpha_min)
                    for c in range(c_):
                        out[n, c, y, x] = a * cur[n, c, y, x] + (1 - a) * hist[n, c, y, x]
                else:
                    k = 1.0
                    out[n, :, y, x] = cur[n, :, y, x]
                cnt[n, 0, y, x] = k
    return out, cnt


@pytest.mark.parametrize("max_count", [None, 4.0])
def test_accumulate_matches_naive(max_count):
    cur = rand(2, 3, 12, 10, seed=1)
    hist = rand(2, 3, 12, 10, seed=2)
    hcount = torch.randint(1, 15, (2, 1, 12, 10), generator=torch.Generator().manual_seed(3)).double()
    valid = rand(2, 1, 12, 10, seed=4) > 0.3
    out, cnt = accumulate(cur, hist, hcount, valid, alpha_min=0.1, max_count=max_count)
    ref, ref_cnt = naive_accumulate(cur, hist, hcount, valid, 0.1, max_count)
    torch.testing.assert_close(out, ref)
    torch.testing.assert_close(cnt, ref_cnt)
    # float masks are accepted too
    out_f, cnt_f = accumulate(cur, hist, hcount, valid.double(), alpha_min=0.1, max_count=max_count)
    torch.testing.assert_close(out_f, ref)
    torch.testing.assert_close(cnt_f, ref_cnt)


def test_running_mean_then_exponential():
    # A static pixel fed samples x_1..x_T: the exact mean while count <= 1/alpha_min, an EMA afterwards.
    samples = rand(12, 1, 3, 1, 1, seed=5)
    alpha_min = 0.25
    hist = cnt = None
    valid = torch.ones(1, 1, 1, 1, dtype=torch.bool)
    ema = None
    for t in range(12):
        hist, cnt = accumulate(samples[t], hist, cnt, valid, alpha_min=alpha_min)
        assert cnt.item() == t + 1
        if t + 1 <= 4:
            torch.testing.assert_close(hist, samples[: t + 1].mean(dim=0))
            ema = hist
        else:
            ema = alpha_min * samples[t] + (1 - alpha_min) * ema
            torch.testing.assert_close(hist, ema)


def test_fresh_start_and_reset_ignore_history():
    cur = rand(1, 3, 4, 5, seed=6)
    out, cnt = accumulate(cur, None, None, None)
    assert torch.equal(out, cur) and torch.equal(cnt, torch.ones(1, 1, 4, 5, dtype=cur.dtype))
    hist = torch.full_like(cur, float("nan"))  # garbage history must not leak into invalid pixels
    hcount = torch.full((1, 1, 4, 5), 7.0, dtype=cur.dtype)
    out, cnt = accumulate(cur, hist, hcount, torch.zeros(1, 1, 4, 5, dtype=torch.bool))
    assert torch.equal(out, cur) and bool((cnt == 1).all())


def test_accumulate_is_differentiable():
    cur = rand(1, 3, 4, 5, seed=7).requires_grad_()
    hist = rand(1, 3, 4, 5, seed=8).requires_grad_()
    hcount = torch.full((1, 1, 4, 5), 2.0, dtype=torch.float64)
    valid = torch.ones(1, 1, 4, 5, dtype=torch.bool)
    out, _ = accumulate(cur, hist, hcount, valid)
    out.sum().backward()
    torch.testing.assert_close(cur.grad, torch.full_like(cur, 1 / 3))
    torch.testing.assert_close(hist.grad, torch.full_like(hist, 2 / 3))


def test_update_count_cap():
    hcount = torch.tensor([[[[1.0, 31.0, 32.0, 5.0]]]])
    valid = torch.tensor([[[[True, True, True, False]]]])
    assert update_count(hcount, valid, max_count=32).flatten().tolist() == [2.0, 32.0, 32.0, 1.0]


def test_moments_match_naive():
    cur = rand(2, 3, 12, 10, seed=9, hi=4)
    hm = rand(2, 1, 12, 10, seed=10, hi=2)
    hm2 = hm * hm + rand(2, 1, 12, 10, seed=11, hi=0.5)
    hcount = torch.randint(1, 10, (2, 1, 12, 10), generator=torch.Generator().manual_seed(12)).double()
    valid = rand(2, 1, 12, 10, seed=13) > 0.3
    mean, mean_sq, var = accumulate_moments(cur, hm, hm2, hcount, valid, alpha_min=0.2)
    for n in range(2):
        for y in range(12):
            for x in range(10):
                lum = sum(LUMA[c] * cur[n, c, y, x].item() for c in range(3))
                if valid[n, 0, y, x]:
                    a = max(1.0 / (hcount[n, 0, y, x].item() + 1), 0.2)
                    m1 = a * lum + (1 - a) * hm[n, 0, y, x].item()
                    m2 = a * lum * lum + (1 - a) * hm2[n, 0, y, x].item()
                else:
                    m1, m2 = lum, lum * lum
                assert mean[n, 0, y, x].item() == pytest.approx(m1, abs=1e-12)
                assert mean_sq[n, 0, y, x].item() == pytest.approx(m2, abs=1e-12)
                assert var[n, 0, y, x].item() == pytest.approx(max(m2 - m1 * m1, 0.0), abs=1e-12)


def test_moments_give_the_sample_variance_of_a_sequence():
    # Grey frames (luminance = value since the weights sum to 1); 4 samples with alpha_min = 0.2 stay an
    # exact mean, so the variance is the population variance of the samples.
    values = [0.5, 1.5, 2.0, 4.0]
    m = m2 = cnt = None
    valid = torch.ones(1, 1, 1, 1, dtype=torch.bool)
    for v in values:
        cur = torch.full((1, 3, 1, 1), v, dtype=torch.float64)
        m, m2, var = accumulate_moments(cur, m, m2, cnt, valid, alpha_min=0.2)
        cnt = update_count(cnt, valid, like=cur)  # the count both accumulators share
    t = torch.tensor(values, dtype=torch.float64)
    assert m.item() == pytest.approx(t.mean().item())
    assert var.item() == pytest.approx(t.var(unbiased=False).item())

    const = torch.full((1, 3, 2, 2), 0.7, dtype=torch.float64)
    _, _, var = accumulate_moments(const, None, None, None, None)
    assert bool((var == 0).all())
