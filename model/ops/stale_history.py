"""A statistical test of whether a reprojected history is stale, read from the 1 spp frame itself.

Motion vectors describe geometry, so where a light moved the warped history passes the depth test and is still
wrong: it lags behind the shading. A spatially denoised frame cannot tell such a change from its own blotches,
since both are errors of the same size and reach. The noisy frame can: its samples are unbiased, so over a
window of B x B pixels their mean estimates what the history's mean should be, with a standard error that the
window's own spread measures. Where the two means differ by many standard errors, the light changed (A-SVGF
finds the same with re-shaded samples, which our frame format does not carry). Fireflies widen the spread, so
the test grows more lenient exactly where the frame is least trustworthy.

``stale_history_z`` is that distance in standard errors, per pixel (each pixel's window centred on it);
``history_trust`` turns it into a weight in [0, 1]: 1 up to ``sigmas``, then a Gaussian fall-off;
``stale_history_trust`` is the two together, the weight its callers use.

One window's 81 samples see a light that moves a little every frame only where the change is large. Over a
region the evidence adds up: where nothing changed each z is about as likely small as large and their root mean
square stays near 1, while a light that moved lifts the z of most windows in reach, whatever the sign of each
change. ``regional_z`` is that root mean square over a wider window, each z capped at ``REGION_Z_CAP`` first so that
a few windows far off (a visible lamp that moved: z in the tens) cannot speak for the whole region; a region whose
z's are too large as a whole distrusts its history even where no single window is sure.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from model.ops.box_filter import box_mean

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
    z = stale_history_z(noisy, history, block)
    trust = history_trust(z, sigmas)
    if region:
        trust = torch.minimum(trust, history_trust(regional_z(z, region), REGION_SIGMAS))
    return trust
