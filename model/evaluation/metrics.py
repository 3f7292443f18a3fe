"""Image and video quality metrics of the benchmark protocol (docs/evaluate.md).

Per frame, on batches of (N, 3, H, W) linear HDR radiance (output and reference at the same resolution):

- PSNR and SSIM on display-encoded images, ``clip(x, 0, 1) ** (1/2.2)`` (``model.ops.tonemap.display_encode``);
- FLIP (NVIDIA's ``flip-evaluator``, LDR-FLIP) on the same display-encoded images;
- SMAPE on the linear HDR radiance.

Per sequence: the temporal error (mean L1 between the frame-to-frame change of the output and that of the
reference) and FovVideoVDP's JOD (``pyfvvdp``, display ``standard_4k``, 30 frames per second).

The low-level functions (``psnr``, ``ssim``, ``flip``, ``smape``, ``temporal_error``) take the images they
compare as given, so their closed-form answers can be tested; ``frame_metrics`` applies the protocol's encodings.
Higher is better for PSNR, SSIM and JOD; lower is better for FLIP, SMAPE and the temporal error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from model.ops.tonemap import display_encode

__all__ = [
    "PSNR_CAP_DB",
    "HIGHER_IS_BETTER",
    "psnr",
    "ssim",
    "flip",
    "smape",
    "temporal_error",
    "frame_metrics",
    "FovVideoVdp",
]

PSNR_CAP_DB = 100.0
"""PSNR of identical images is infinite; it is reported as this cap instead (an MSE of 1e-10 on [0, 1] images),
so that per-sequence means and the JSON report stay finite numbers."""

SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_K1, SSIM_K2 = 0.01, 0.03  # Wang et al. 2004; with data range L = 1, C1 = (K1 L)^2, C2 = (K2 L)^2
SMAPE_EPSILON = 0.01  # keeps SMAPE finite where both images are black
VDP_DISPLAY = "standard_4k"
VDP_FRAMES_PER_SECOND = 30

HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "flip": False, "smape": False, "temporal_error": False,
                    "fvvdp_jod": True}


def _check_pair(a: torch.Tensor, b: torch.Tensor) -> None:
    if a.shape != b.shape:
        raise ValueError(f"images to compare differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
    if a.dim() != 4:
        raise ValueError(f"expected (N, C, H, W) images, got shape {tuple(a.shape)}")


def psnr(a: torch.Tensor, b: torch.Tensor, peak: float = 1.0) -> torch.Tensor:
    """Peak signal-to-noise ratio in dB per image, (N, C, H, W) -> (N,), capped at PSNR_CAP_DB."""
    _check_pair(a, b)
    mse = (a.double() - b.double()).square().mean(dim=(1, 2, 3))
    floor = peak * peak * 10.0 ** (-PSNR_CAP_DB / 10.0)
    return (10.0 * torch.log10(peak * peak / mse.clamp_min(floor))).to(a.dtype)


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64, device=device) - (size - 1) / 2
    weights = torch.exp(-(x * x) / (2 * sigma * sigma))
    return (weights / weights.sum()).to(dtype)


def _gaussian_filter_valid(x: torch.Tensor, window: torch.Tensor) -> torch.Tensor:
    """Separable Gaussian on every channel of (N, C, H, W), without padding ('valid': output shrinks by k-1)."""
    channels = x.shape[1]
    k = window.numel()
    horizontal = window.view(1, 1, 1, k).expand(channels, 1, 1, k)
    vertical = window.view(1, 1, k, 1).expand(channels, 1, k, 1)
    return F.conv2d(F.conv2d(x, horizontal, groups=channels), vertical, groups=channels)


def ssim(a: torch.Tensor, b: torch.Tensor, data_range: float = 1.0) -> torch.Tensor:
    """Structural similarity per image, (N, C, H, W) -> (N,): the mean SSIM map over pixels and channels.

    Wang et al. 2004: Gaussian window 11 x 11 with sigma 1.5, K1 = 0.01, K2 = 0.03, each channel on its own,
    statistics only where the whole window lies inside the image (no padding, as in the reference code).
    """
    _check_pair(a, b)
    if min(a.shape[2:]) < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got "
                         f"{a.shape[3]}x{a.shape[2]}")
    a, b = a.double(), b.double()
    window = _gaussian_window(SSIM_WINDOW, SSIM_SIGMA, a.dtype, a.device)
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    mean_a, mean_b = _gaussian_filter_valid(a, window), _gaussian_filter_valid(b, window)
    var_a = _gaussian_filter_valid(a * a, window) - mean_a * mean_a
    var_b = _gaussian_filter_valid(b * b, window) - mean_b * mean_b
    covariance = _gaussian_filter_valid(a * b, window) - mean_a * mean_b
    ssim_map = ((2 * mean_a * mean_b + c1) * (2 * covariance + c2)) / (
        (mean_a * mean_a + mean_b * mean_b + c1) * (var_a + var_b + c2))
    return ssim_map.mean(dim=(1, 2, 3)).float()


def flip(test: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Mean LDR-FLIP error per image, (N, 3, H, W) in [0, 1] -> (N,); 0 for identical images.

    Inputs are display-encoded (gamma) images, which FLIP's LDR mode takes as sRGB-encoded; FLIP's default
    viewing condition (67 pixels per degree) applies. Computed by NVIDIA's ``flip-evaluator`` on the CPU.
    """
    import flip_evaluator

    _check_pair(test, reference)
    if test.shape[1] != 3:
        raise ValueError(f"FLIP compares RGB images, got {test.shape[1]} channels")
    low = min(float(test.min()), float(reference.min()))
    high = max(float(test.max()), float(reference.max()))
    if low < 0.0 or high > 1.0:
        # flip-evaluator exits the process on bad input; refuse here with a message instead.
        raise ValueError(f"LDR-FLIP needs images in [0, 1], got values in [{low:g}, {high:g}]")

    def hwc(images: torch.Tensor, index: int) -> np.ndarray:
        return np.ascontiguousarray(images[index].detach().float().cpu().permute(1, 2, 0).numpy())

    errors = []
    for index in range(test.shape[0]):
        _, mean_error, _ = flip_evaluator.evaluate(hwc(reference, index), hwc(test, index), "LDR",
                                                   inputsRGB=True, applyMagma=False, computeMeanError=True)
        errors.append(float(mean_error))
    return torch.tensor(errors, dtype=torch.float32)


def smape(a: torch.Tensor, b: torch.Tensor, epsilon: float = SMAPE_EPSILON) -> torch.Tensor:
    """Symmetric mean absolute percentage error per image, mean of |a - b| / (|a| + |b| + epsilon): (N,)."""
    _check_pair(a, b)
    a, b = a.double(), b.double()
    return ((a - b).abs() / (a.abs() + b.abs() + epsilon)).mean(dim=(1, 2, 3)).float()


def temporal_error(outputs: torch.Tensor, references: torch.Tensor,
                   camera_cuts: Sequence[bool] | torch.Tensor | None = None) -> float | None:
    """Mean L1 between the frame-to-frame change of the output and that of the reference, over a sequence.

    ``outputs`` and ``references`` are (T, C, H, W) frames in order. Pairs (t-1, t) where frame t starts after
    a camera cut (``camera_cuts[t]`` True) are skipped: across a cut the change means nothing. Each remaining
    pair counts equally. None when no pair remains (a one-frame sequence).
    """
    if outputs.shape != references.shape or outputs.dim() != 4:
        raise ValueError(f"expected two (T, C, H, W) sequences of one shape, got {tuple(outputs.shape)} "
                         f"and {tuple(references.shape)}")
    frames = outputs.shape[0]
    cuts = [False] * frames if camera_cuts is None else [bool(c) for c in camera_cuts]
    if len(cuts) != frames:
        raise ValueError(f"camera_cuts has {len(cuts)} entries for {frames} frames")
    pairs = [t for t in range(1, frames) if not cuts[t]]
    if not pairs:
        return None
    later = torch.tensor(pairs, device=outputs.device)
    output_change = outputs[later].double() - outputs[later - 1].double()
    reference_change = references[later].double() - references[later - 1].double()
    return float((output_change - reference_change).abs().mean())


def frame_metrics(output: torch.Tensor, reference: torch.Tensor) -> dict[str, torch.Tensor]:
    """The per-frame metrics of the protocol for linear HDR (N, 3, H, W) batches: name -> (N,) values."""
    _check_pair(output, reference)
    output_ldr, reference_ldr = display_encode(output), display_encode(reference)
    return {
        "psnr": psnr(output_ldr, reference_ldr).float().cpu(),
        "ssim": ssim(output_ldr, reference_ldr).cpu(),
        "flip": flip(output_ldr, reference_ldr),
        "smape": smape(output, reference).cpu(),
    }


class FovVideoVdp:
    """FovVideoVDP (``pyfvvdp``) on whole sequences: display ``standard_4k``, 30 frames per second.

    The metric model is loaded once (it reads its configuration and CSF tables shipped inside the package; nothing
    is downloaded). If it cannot be loaded, ``unavailable_reason`` says why and ``jod`` is not to be called:
    evaluation reports the JOD as None with that reason rather than failing the whole run.
    """

    def __init__(self, device: torch.device | str = "cpu") -> None:
        self._metric = None
        self.unavailable_reason: str | None = None
        try:
            import pyfvvdp

            self._metric = pyfvvdp.fvvdp(display_name=VDP_DISPLAY, heatmap=None, quiet=True,
                                         device=torch.device(device))
        except (ImportError, OSError, RuntimeError, KeyError) as error:
            # Missing package, missing shipped data file, or a torch incompatibility: reported, not fatal.
            self.unavailable_reason = f"pyfvvdp could not be loaded: {type(error).__name__}: {error}"

    @property
    def available(self) -> bool:
        return self._metric is not None

    def jod(self, outputs: torch.Tensor, references: torch.Tensor) -> float:
        """JOD (10 = no visible difference) of display-encoded (T, 3, H, W) frames in [0, 1] against references."""
        if self._metric is None:
            raise RuntimeError(self.unavailable_reason or "FovVideoVDP is not available")
        if outputs.shape != references.shape or outputs.dim() != 4 or outputs.shape[1] != 3:
            raise ValueError(f"expected two (T, 3, H, W) sequences of one shape, got {tuple(outputs.shape)} "
                             f"and {tuple(references.shape)}")
        # pyfvvdp reads display-encoded float frames only as float32 (other float types are rejected).
        test = outputs.detach().float().clamp(0.0, 1.0).contiguous()
        reference = references.detach().float().clamp(0.0, 1.0).contiguous()
        quality, _ = self._metric.predict(test, reference, dim_order="FCHW", frames_per_second=VDP_FRAMES_PER_SECOND)
        value = float(quality)
        if not math.isfinite(value):
            raise RuntimeError(f"FovVideoVDP returned a non-finite JOD ({value})")
        return value
