"""Tone curves: round trips, closed-form values, gradients; luminance against the Rec. 709 formula."""

import math

import pytest
import torch

from model.ops.tonemap import (
    display_decode,
    display_encode,
    log_tonemap,
    log_tonemap_inverse,
    luminance,
    mulaw,
    mulaw_inverse,
)


def hdr(seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    # radiance spanning 1e-4 .. 1e3, plus exact zeros
    x = torch.exp(torch.empty(1, 3, 12, 10, dtype=dtype).uniform_(math.log(1e-4), math.log(1e3), generator=g))
    x[..., 0, :] = 0.0
    return x


@pytest.mark.parametrize("dtype,rtol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
def test_round_trips(dtype, rtol):
    x = hdr(1, dtype)
    torch.testing.assert_close(mulaw_inverse(mulaw(x)), x, rtol=rtol, atol=1e-9)
    torch.testing.assert_close(mulaw_inverse(mulaw(x, mu=16), mu=16), x, rtol=rtol, atol=1e-9)
    torch.testing.assert_close(log_tonemap_inverse(log_tonemap(x)), x, rtol=rtol, atol=1e-9)
    ldr = x.clamp(0, 1)
    torch.testing.assert_close(display_decode(display_encode(x)), ldr, rtol=rtol * 10, atol=1e-9)


def test_closed_form_values():
    x = torch.tensor([0.0, 1.0, 0.5, 4.0], dtype=torch.float64)
    torch.testing.assert_close(mulaw(x[:2]), torch.tensor([0.0, 1.0], dtype=torch.float64))
    assert mulaw(x[2:3]).item() == pytest.approx(math.log(1 + 5000 * 0.5) / math.log(5001))
    torch.testing.assert_close(log_tonemap(x), torch.log(1 + x))
    enc = display_encode(torch.tensor([-1.0, 0.0, 0.25, 1.0, 7.0], dtype=torch.float64))
    torch.testing.assert_close(enc, torch.tensor([0.0, 0.0, 0.25 ** (1 / 2.2), 1.0, 1.0], dtype=torch.float64))


def test_display_encode_gradient_is_finite():
    x = torch.tensor([-0.5, 0.0, 1e-6, 0.5, 2.0], dtype=torch.float64, requires_grad=True)
    display_encode(x).sum().backward()
    assert bool(torch.isfinite(x.grad).all())
    assert x.grad[0].item() == 0.0 and x.grad[-1].item() == 0.0
    assert x.grad[3].item() == pytest.approx(0.5 ** (1 / 2.2 - 1) / 2.2)


def test_luminance():
    rgb = hdr(2)
    lum = luminance(rgb)
    assert lum.shape == (1, 1, 12, 10)
    for y in range(12):
        for x in range(10):
            r, g, b = rgb[0, :, y, x].tolist()
            assert lum[0, 0, y, x].item() == pytest.approx(0.2126 * r + 0.7152 * g + 0.0722 * b, rel=1e-12)
    torch.testing.assert_close(luminance(torch.ones(1, 3, 2, 2)), torch.ones(1, 1, 2, 2))
    with pytest.raises(ValueError):
        luminance(torch.ones(1, 4, 2, 2))
