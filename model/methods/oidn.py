"""Intel Open Image Denoise (through `pyoidn`) as the outside peer every method is timed and scored against.

OIDN's RT filter runs on the CPU here, one image at a time, with albedo and normal as clean auxiliary images
(`clean_aux=True`: our guides are rendered noise-free, so OIDN need not prefilter them). The presets are OIDN's
own quality levels: "fast", "balanced", "high". It is spatial only, so it keeps no state; at scale 2 its
output is bicubic-upscaled like the other baselines. Not a torch model: `parameter_count()` is 0.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pyoidn
import torch

from model.methods.base import FrameBatch, State
from model.methods.baselines import RenderResolutionFilter
from model.methods.registry import MethodSpec, register

__all__ = ["OIDN", "QUALITIES", "intercepted_oidn", "oidn_albedo", "oidn_denoise", "oidn_device_for"]

log = logging.getLogger(__name__)

QUALITIES = ("fast", "balanced", "high")


def oidn_albedo(frame: FrameBatch) -> torch.Tensor:
    """The albedo guide OIDN should see: diffuse + specular albedo, clipped to [0, 1], when both are given.

    OIDN's albedo is "the reflectance that modulates the noisy radiance": for metals and glass, which have no
    diffuse albedo, its documentation asks for the specular reflectance instead. With the diffuse albedo alone,
    a mirror or a metal would look black in the guide and OIDN would blur the detail it reflects.
    """
    if frame.specular_albedo is None:
        return frame.albedo
    return (frame.albedo + frame.specular_albedo).clamp(0.0, 1.0)


def _to_hwc(image: torch.Tensor) -> np.ndarray:
    """One (3, H, W) tensor as the contiguous float32 (H, W, 3) NumPy array pyoidn takes."""
    return np.ascontiguousarray(image.detach().to("cpu", torch.float32).permute(1, 2, 0).numpy())


Denoise = Callable[[FrameBatch, str], torch.Tensor]
_INTERCEPTOR = threading.local()


@contextmanager
def intercepted_oidn(interceptor: Callable[[Denoise, FrameBatch, str], torch.Tensor]) -> Iterator[None]:
    """For the block, this thread's ``oidn_denoise(frame, quality)`` calls ``interceptor(denoise, frame, quality)``,
    which must return ``denoise(frame, quality)``'s result: the speed benchmark times OIDN inside a step so, and a
    CUDA graph (model.deployment.cuda_graph) runs OIDN between its captured parts. An interceptor set inside another
    one's block wraps it (its ``denoise`` is the outer interceptor's call)."""
    outer = getattr(_INTERCEPTOR, "call", None)
    if outer is None:
        _INTERCEPTOR.call = interceptor
    else:
        _INTERCEPTOR.call = lambda denoise, frame, quality: interceptor(
            lambda inner_frame, inner_quality: outer(denoise, inner_frame, inner_quality), frame, quality)
    try:
        yield
    finally:
        _INTERCEPTOR.call = outer


def oidn_denoise(frame: FrameBatch, quality: str) -> torch.Tensor:
    """OIDN's RT filter on every frame of the batch (HDR, albedo + normal, clean aux), at render resolution.

    The one place OIDN is called: the `oidn` peer, `oidn-taa` and the `fused` family's spatial estimate all
    use it, so they denoise with exactly the same settings. A frame on a CUDA device is denoised by OIDN's CUDA
    device when this pyoidn build has one, else (after one warning) on the CPU. ``intercepted_oidn`` may wrap it.
    """
    interceptor = getattr(_INTERCEPTOR, "call", None)
    if interceptor is not None:
        return interceptor(_denoise, frame, quality)
    return _denoise(frame, quality)


def _denoise(frame: FrameBatch, quality: str) -> torch.Tensor:
    if quality not in QUALITIES:
        raise KeyError(f"OIDN has no quality {quality!r}; qualities: {', '.join(QUALITIES)}")
    albedo = oidn_albedo(frame)
    if oidn_device_for(frame.device) == "cuda":
        try:
            return _denoise_cuda(frame, albedo, quality)
        except (TypeError, ValueError, RuntimeError) as error:  # this pyoidn build has no CUDA device after all
            _CUDA_STATE["usable"] = False
            log.warning("OIDN's CUDA device failed (%s); denoising on the CPU from now on", error)
    outputs = []
    for index in range(frame.batch_size):
        denoised = pyoidn.denoise(_to_hwc(frame.color[index]), _to_hwc(albedo[index]),
                                  _to_hwc(frame.normal[index]), hdr=True, clean_aux=True, quality=quality)
        outputs.append(torch.from_numpy(denoised).permute(2, 0, 1))
    return torch.stack(outputs).to(device=frame.device, dtype=frame.color.dtype)


_CUDA_STATE: dict[str, bool] = {}


def _cuda_oidn_usable() -> bool:
    return _CUDA_STATE.get("usable", True)


def oidn_device_for(device: torch.device | str) -> str:
    """Which OIDN device denoises frames that live on `device`: "cuda" or "cpu".

    "cuda" only for a CUDA frame, when this pyoidn build has a CUDA device that supports that GPU and it has
    not failed in this process; everything else is denoised on the CPU (benchmarks print this, so a GPU time
    is never silently a CPU one).
    """
    device = torch.device(device)
    if device.type != "cuda" or not _cuda_oidn_usable():
        return "cpu"
    try:
        supported = bool(pyoidn.Device.is_cuda_available(device.index or 0))
    except (AttributeError, OSError, RuntimeError):  # a build without the query, or without a CUDA library
        supported = False
    return "cuda" if supported else "cpu"


def _denoise_cuda(frame: FrameBatch, albedo: torch.Tensor, quality: str) -> torch.Tensor:
    """OIDN on the GPU the frame lives on (pyoidn takes CUDA tensors and runs its CUDA device on them)."""
    outputs = []
    for index in range(frame.batch_size):
        def hwc(image: torch.Tensor) -> torch.Tensor:
            return image[index].detach().to(torch.float32).permute(1, 2, 0).contiguous()

        denoised = pyoidn.denoise(hwc(frame.color), hwc(albedo), hwc(frame.normal), hdr=True, clean_aux=True,
                                  quality=quality)
        outputs.append(torch.as_tensor(denoised, device=frame.device).permute(2, 0, 1))
    return torch.stack(outputs).to(frame.color.dtype)


class OIDN(RenderResolutionFilter):
    """OIDN RT filter with albedo and normal guides (HDR, clean aux) at the preset's quality."""

    name = "oidn"

    def __init__(self, preset: str = "high", scale: int = 1):
        super().__init__(preset, scale)
        if preset not in QUALITIES:
            raise KeyError(f"{self.name} has no preset {preset!r}; presets: {', '.join(QUALITIES)}")

    def filter_frame(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        return oidn_denoise(frame, self.preset), {}


register(MethodSpec(
    name=OIDN.name,
    description="Intel Open Image Denoise (pyoidn RT filter, albedo + normal, clean aux), the outside peer",
    factory=lambda preset, scale: OIDN(preset, scale),
    presets=QUALITIES,
    default_preset="high",
    scales=(1, 2),
    optional_buffers=("specular_albedo",),  # OIDN's albedo guide adds the specular albedo (oidn_albedo)
))
