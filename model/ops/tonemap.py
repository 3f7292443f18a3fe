"""Transfer functions between linear HDR radiance and the compressed ranges networks and metrics use.

Each curve comes as a forward/inverse pair (as in OIDN's ``training/color.py``), so a method can compress its
inputs and expand its outputs without re-deriving the formula. All are elementwise on any tensor shape; the
HDR curves expect non-negative radiance (the frame format guarantees it).
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "mulaw",
    "mulaw_inverse",
    "log_tonemap",
    "log_tonemap_inverse",
    "display_encode",
    "display_decode",
    "luminance",
    "REC709_LUMA",
]

REC709_LUMA = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB luminance weights for linear RGB."""

DISPLAY_GAMMA = 2.2


def mulaw(x: torch.Tensor, mu: float = 5000.0) -> torch.Tensor:
    """mu-law compression (MUNet): ``log(1 + mu x) / log(1 + mu)``; maps [0, 1] onto [0, 1], x >= 0."""
    return torch.log1p(mu * x) / math.log1p(mu)


def mulaw_inverse(y: torch.Tensor, mu: float = 5000.0) -> torch.Tensor:
    """Inverse of :func:`mulaw`: ``((1 + mu) ** y - 1) / mu`` (via expm1 to keep precision near 0)."""
    return torch.expm1(y * math.log1p(mu)) / mu


def log_tonemap(x: torch.Tensor) -> torch.Tensor:
    """Log tone map (JNDS): ``log(1 + x)``, x >= 0. Unbounded, so very bright pixels stay distinguishable."""
    return torch.log1p(x)


def log_tonemap_inverse(y: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`log_tonemap`: ``exp(y) - 1``."""
    return torch.expm1(y)


def display_encode(x: torch.Tensor) -> torch.Tensor:
    """Benchmark-protocol LDR image: ``clip(x, 0, 1) ** (1 / 2.2)`` (docs/evaluate.md), on which PSNR/SSIM/FLIP run.

    Values are exactly the formula's. The gradient is kept finite at 0 (where ``x ** (1/2.2)`` has an infinite
    slope) by routing x <= 0 through a constant branch, so the function can also sit inside a training loss.
    """
    c = x.clamp(0.0, 1.0)
    pos = c > 0
    safe = torch.where(pos, c, torch.ones_like(c))  # the pow never sees 0, so no inf * 0 = NaN in backward
    return torch.where(pos, safe ** (1.0 / DISPLAY_GAMMA), torch.zeros_like(c))


def display_decode(y: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`display_encode` on its range [0, 1]: ``clip(y, 0, 1) ** 2.2`` (clipping is not undone)."""
    return y.clamp(0.0, 1.0) ** DISPLAY_GAMMA


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Rec. 709 luminance of linear RGB (N, 3, H, W) -> (N, 1, H, W)."""
    if rgb.dim() != 4 or rgb.shape[1] != 3:
        raise ValueError(f"expected (N, 3, H, W) linear RGB, got {tuple(rgb.shape)}")
    r, g, b = rgb[:, 0:1], rgb[:, 1:2], rgb[:, 2:3]
    return REC709_LUMA[0] * r + REC709_LUMA[1] * g + REC709_LUMA[2] * b
