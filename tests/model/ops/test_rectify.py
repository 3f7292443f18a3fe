"""History rectification against a naive per-pixel loop, and the cases it exists for."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model.ops.rectify import neighbourhood_clamp, rgb_to_ycocg, variance_clip, ycocg_to_rgb


def _naive(history: np.ndarray, guide: np.ndarray, size: int, gamma: float | None) -> np.ndarray:
    """Per pixel, per YCoCg channel: the window's min/max (gamma None) or mean +- gamma * std, border replicated."""
    to_ycocg = np.array([[0.25, 0.5, 0.25], [0.5, 0.0, -0.5], [-0.25, 0.5, -0.25]])
    to_rgb = np.linalg.inv(to_ycocg)
    n, _, h, w = guide.shape
    r = size // 2
    out = np.zeros_like(history)
    for b in range(n):
        g = np.einsum("ij,jhw->ihw", to_ycocg, guide[b])
        hist = np.einsum("ij,jhw->ihw", to_ycocg, history[b])
        for y in range(h):
            for x in range(w):
                ys = [min(max(y + dy, 0), h - 1) for dy in range(-r, r + 1) for _ in range(-r, r + 1)]
                xs = [min(max(x + dx, 0), w - 1) for _ in range(-r, r + 1) for dx in range(-r, r + 1)]
                window = g[:, ys, xs]
                if gamma is None:
                    low, high = window.min(axis=1), window.max(axis=1)
                else:
                    mean, std = window.mean(axis=1), window.std(axis=1)
                    low, high = mean - gamma * std, mean + gamma * std
                out[b, :, y, x] = to_rgb @ np.clip(hist[:, y, x], low, high)
    return out


@pytest.mark.parametrize("size", [3, 5])
def test_clamp_and_clip_match_a_naive_loop(size):
    rng = np.random.default_rng(3)
    guide = rng.uniform(0, 1, (2, 3, 7, 9))
    history = rng.uniform(-0.5, 1.5, (2, 3, 7, 9))
    g, hist = torch.from_numpy(guide), torch.from_numpy(history)
    np.testing.assert_allclose(neighbourhood_clamp(hist, g, size).numpy(), _naive(history, guide, size, None),
                               atol=1e-10)
    for gamma in (0.5, 1.0, 2.0):
        np.testing.assert_allclose(variance_clip(hist, g, size, gamma).numpy(),
                                   _naive(history, guide, size, gamma), atol=1e-9)


def test_ycocg_round_trip_is_exact():
    rgb = torch.rand(1, 3, 4, 4, dtype=torch.float64)
    torch.testing.assert_close(ycocg_to_rgb(rgb_to_ycocg(rgb)), rgb, atol=1e-15, rtol=0)


def test_a_stale_history_is_pulled_to_the_current_frame_and_a_plausible_one_is_kept():
    guide = torch.full((1, 3, 5, 5), 0.3)
    guide[..., 2:, :] = 0.6  # an edge: the window around row 2 spans 0.3 .. 0.6
    stale = torch.full((1, 3, 5, 5), 5.0)  # a light that moved away: far brighter than anything around now
    clamped = neighbourhood_clamp(stale, guide)
    assert torch.allclose(clamped[..., 0, :], torch.tensor(0.3)) and torch.allclose(clamped[..., 4, :],
                                                                                       torch.tensor(0.6))
    plausible = torch.full((1, 3, 5, 5), 0.45)  # between the two sides of the edge: kept by min/max
    assert torch.allclose(neighbourhood_clamp(plausible, guide)[..., 2, :], torch.tensor(0.45))
    # A flat neighbourhood has no spread: the variance clip returns the guide itself.
    assert torch.allclose(variance_clip(stale, guide)[..., 0, :], torch.tensor(0.3), atol=1e-3)  # float32 moments


def test_bad_shapes_and_parameters_are_named():
    with pytest.raises(ValueError, match="must both be"):
        variance_clip(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
    with pytest.raises(ValueError, match="odd"):
        neighbourhood_clamp(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), size=2)
    with pytest.raises(ValueError, match="gamma"):
        variance_clip(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 4), gamma=-1)
