"""Albedo demodulation, one rule for every method.

Temporal and spatial filters work on illumination = radiance / divisor and multiply the same divisor back,
so texture comes sharp from the current frame's albedo while only the smooth illumination is blurred.
The divisor is albedo + 0.01: that caps the amplification of dark albedos at 100x. Pixels with no diffuse
albedo at all (sky, metal, glass: the generator writes 0) keep their radiance (divisor 1); divided by 0.01
they would sit 100x above their neighbours inside shared filter windows and leave halos after remodulation.
Any positive divisor round-trips exactly.
"""

from __future__ import annotations

import torch

DEMODULATION_EPS = 1e-2
NO_DIFFUSE_ALBEDO = 1e-3


def demodulation_divisor(albedo: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) divisor for radiance of the same shape: albedo + eps, or 1 where there is no albedo."""
    has_albedo = albedo.amax(dim=1, keepdim=True) > NO_DIFFUSE_ALBEDO
    return torch.where(has_albedo, albedo + DEMODULATION_EPS, torch.ones_like(albedo))


def demodulate(color: torch.Tensor, albedo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(illumination, divisor): remodulate with `illumination * divisor`."""
    divisor = demodulation_divisor(albedo)
    return color / divisor, divisor
