"""The native stale-history test and sample-mean update equal the torch ops they replace, on seeded frames."""

from unittest import mock

import pytest
import torch

from model.ops import native
from model.ops.native import stale
from model.ops.sample_mean import update_sample_mean
from model.ops.stale_history import stale_history_trust


def _frames(seed: int, h: int, w: int, n: int = 1, channels: int = 3):
    g = torch.Generator().manual_seed(seed)
    history = torch.rand(n, channels, h, w, generator=g) * 2
    noisy = history * (1 + 0.3 * torch.randn(n, channels, h, w, generator=g)).clamp_min(0)
    noisy[..., : h // 3, : w // 2] *= 1.5  # a light that changed: low trust there
    noisy[..., -3:, :] = history[..., -3:, :]  # no change at all: the floors only
    noisy[..., 0, 0] += 40  # a firefly
    return noisy, history


def _torch(function, *arguments, **keywords):
    native.set_enabled(False)
    try:
        return function(*arguments, **keywords)
    finally:
        native.set_enabled(True)


@pytest.mark.parametrize("h, w", [(37, 53), (5, 4), (509, 515)])
@pytest.mark.parametrize("region", [0, 33])
@pytest.mark.parametrize("sigmas", [0.5, 1.0])
def test_trust_equals_torch(h, w, region, sigmas):
    noisy, history = _frames(h * w + region, h, w)
    with torch.no_grad():
        expected = _torch(stale_history_trust, noisy, history, sigmas, region, 9)
        with mock.patch.object(stale, "native", wraps=native) as spy:
            trust = stale_history_trust(noisy, history, sigmas, region, 9)
    assert spy.call.called
    assert trust.shape == expected.shape == (1, 1, h, w)
    torch.testing.assert_close(trust, expected, atol=1e-5, rtol=0)
    if h > 9:  # a window smaller than the image: both answers occur
        assert (expected < 0.5).any() and (expected == 1).any()


@pytest.mark.parametrize("h, w", [(37, 53), (509, 515)])
@pytest.mark.parametrize("stale_sigmas, region", [(0.0, 0), (1.0, 0), (2.0, 33)])
@pytest.mark.parametrize("with_spread", [True, False])
def test_update_equals_torch(h, w, stale_sigmas, region, with_spread):
    g = torch.Generator().manual_seed(h + int(10 * stale_sigmas) + region)
    noisy, mean = _frames(h + w, h, w, channels=9)
    count = torch.randint(0, 9, (1, 1, h, w), generator=g).float()
    valid = torch.rand(1, 1, h, w, generator=g) > 0.3
    spread = (torch.rand(1, 1, h, w, generator=g) * 1.4 - 0.2) if with_spread else None  # clamped to [0, 1]
    arguments = (noisy, mean, count, valid, 8, stale_sigmas)
    with torch.no_grad():
        expected_mean, expected_count = _torch(update_sample_mean, *arguments, spread=spread, stale_region=region)
        with mock.patch.object(stale, "native", wraps=native) as spy:
            new_mean, new_count = update_sample_mean(*arguments, spread=spread, stale_region=region)
    assert spy.call.called
    if stale_sigmas == 0:  # the same float32 operations in the same order
        assert torch.equal(new_count, expected_count) and torch.equal(new_mean, expected_mean)
    # the trust's rounding (a few 1e-6) scaled by counts up to 8
    torch.testing.assert_close(new_count, expected_count, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(new_mean, expected_mean, atol=1e-5, rtol=1e-5)
    assert (expected_count == 1).any() and (expected_count == 8).any() and valid.any() and (~valid).any()


def test_two_images_take_the_torch_path():
    noisy, history = _frames(7, 37, 53, n=2)
    count, valid = torch.full((2, 1, 37, 53), 3.0), torch.ones(2, 1, 37, 53, dtype=torch.bool)
    with torch.no_grad(), mock.patch.object(stale, "native", wraps=native) as spy:
        trust = stale_history_trust(noisy, history, 1.0, 33, 9)
        new_mean, new_count = update_sample_mean(noisy, history, count, valid, 8, 2.0, stale_region=33)
    assert not spy.call.called
    assert trust.shape == (2, 1, 37, 53) and new_mean.shape == noisy.shape and new_count.shape == count.shape


def test_torch_path_where_not_usable():
    noisy, history = _frames(8, 37, 53)
    with mock.patch.object(stale, "native", wraps=native) as spy, torch.enable_grad():  # gradients: not usable
        stale_history_trust(noisy, history, 1.0, 33, 9)
    assert not spy.call.called


def test_even_windows_are_refused():
    noisy, history = _frames(9, 37, 53)
    with torch.no_grad():
        with pytest.raises(ValueError):
            stale_history_trust(noisy, history, 1.0, 0, 8)
        with pytest.raises(ValueError):
            stale_history_trust(noisy, history, 1.0, 32, 9)


def test_views_of_wider_frames():
    noisy, history = _frames(10, 53, 37, channels=9)
    history = history.transpose(2, 3).contiguous().transpose(2, 3)  # not contiguous
    with torch.no_grad():
        expected = _torch(stale_history_trust, noisy[:, 3:6], history[:, :3], 1.0, 33, 9)
        trust = stale_history_trust(noisy[:, 3:6], history[:, :3], 1.0, 33, 9)
    torch.testing.assert_close(trust, expected, atol=1e-5, rtol=0)
