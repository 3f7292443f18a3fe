"""A statistical test of whether a reprojected history is stale, read from the 1 spp frame itself.

Motion vectors describe geometry, so where a light moved the warped history passes the depth test and is still
wrong: it lags behind the shading. A spatially denoised frame cannot tell such a change from its own blotches, but
the noisy frame can: over a B x B window its unbiased samples' mean estimates what the history's mean should be,
with a standard error the window's own spread measures (A-SVGF finds the same with re-shaded samples, which our
frame format does not carry). Fireflies widen the spread, so the test grows lenient where the frame is least
trustworthy. ``stale_history_z`` is that distance in standard errors per pixel; ``history_trust`` turns it into a
weight in [0, 1] (1 up to ``sigmas``, then a Gaussian fall-off); ``stale_history_trust`` is the two together.
``regional_z`` is the root mean square of the z's over a wider window: where nothing changed it stays near 1, and a
light that moved a little everywhere lifts it though no single window is sure. Each z is capped at ``REGION_Z_CAP``
first, so a few windows far off (a visible lamp that moved) cannot speak for the whole region.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from model.ops import native
from model.ops.box_filter import box_mean
from model.ops.native.stale import stale_trust

__all__ = ["stale_history_z", "history_trust", "regional_z", "stale_history_trust", "RELATIVE_FLOOR",
           "REGION_SIGMAS", "REGION_Z_CAP"]

RELATIVE_FLOOR = 0.02  # a 2% change of the mean is never significant: references and history carry that much
# A region's root mean square z past this is a change. Where nothing changed it sits near 1, a little under (the
# floor above shrinks small z's); chosen with a 33-pixel region on the validation split and the seed-8 moving-light
# renders.
REGION_SIGMAS = 1.2
REGION_Z_CAP = 4.0  # no window counts for more than this in its region's root mean square (chosen with it)


def _check_odd(name: str, value: int) -> None:
    if value < 1 or value % 2 == 0:  # a window centred on its pixel
        raise ValueError(f"{name} must be odd and positive, got {value}")


def stale_history_z(noisy: torch.Tensor, history: torch.Tensor, block: int = 9) -> torch.Tensor:
    """|mean(noisy) - mean(history)| / standard error over each pixel's block x block window, (N, 1, H, W).

    ``noisy`` and ``history`` are linear radiance (N, 3, H, W) at one resolution; both are reduced to the mean of
    their channels. The standard error is the noisy window's standard deviation / block, with a floor of
    ``RELATIVE_FLOOR`` of the history's mean (and 1e-3 absolute) so flat, noise-free windows do not divide by 0.
    """
    if noisy.dim() != 4 or noisy.shape[1] != 3 or noisy.shape != history.shape:
        raise ValueError(f"noisy and history must both be (N, 3, H, W) of one shape, got {tuple(noisy.shape)} and "
                         f"{tuple(history.shape)}")
    _check_odd("block", block)
    value, past = noisy.mean(dim=1, keepdim=True), history.mean(dim=1, keepdim=True)
    mean, past_mean, square = box_mean(torch.cat([value, past, value * value], dim=1), block).split(1, dim=1)
    variance = (square - mean * mean).clamp_min(0.0)
    error = torch.sqrt(variance / block ** 2 + (RELATIVE_FLOOR * past_mean) ** 2 + 1e-6)
    return (mean - past_mean).abs() / error


def history_trust(z: torch.Tensor, sigmas: float) -> torch.Tensor:
    """exp(-max(z - sigmas, 0)^2 / 2): full trust up to ``sigmas`` standard errors, falling off beyond."""
    return torch.exp(-F.relu(z - sigmas) ** 2 / 2)


def regional_z(z: torch.Tensor, window: int, cap: float = REGION_Z_CAP) -> torch.Tensor:
    """sqrt(mean of min(z, cap)^2) over each pixel's window x window neighbourhood (cut at the border), (N, 1, H, W)."""
    if z.dim() != 4 or z.shape[1] != 1:
        raise ValueError(f"z must be (N, 1, H, W), got {tuple(z.shape)}")
    _check_odd("window", window)
    capped = z.clamp_max(cap)
    return torch.sqrt(box_mean(capped * capped, window))


def stale_history_trust(noisy: torch.Tensor, history: torch.Tensor, sigmas: float, region: int = 0,
                        block: int = 9) -> torch.Tensor:
    """How far to trust ``history`` against the 1 spp frame ``noisy``, (N, 1, H, W) in [0, 1]: ``history_trust`` of
    ``stale_history_z`` at ``sigmas``, and with a ``region`` (odd window side, 0: none) the lesser of that and the
    region's trust, ``history_trust(regional_z(z, region), REGION_SIGMAS)``."""
    if (noisy.dim() == 4 and noisy.shape[0] == 1 and noisy.shape[1] == 3 and noisy.shape == history.shape
            and native.usable("stale", noisy, history)):  # one image: the whole test in one native call
        _check_odd("block", block)
        if region:
            _check_odd("window", region)
        return stale_trust(noisy, history, sigmas, region, block, RELATIVE_FLOOR, REGION_Z_CAP, REGION_SIGMAS)
    z = stale_history_z(noisy, history, block)
    trust = history_trust(z, sigmas)
    if region:
        trust = torch.minimum(trust, history_trust(regional_z(z, region), REGION_SIGMAS))
    return trust
