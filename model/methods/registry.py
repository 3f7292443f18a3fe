"""Method registry: names and size presets to constructors, parameter counts and FLOPs per pixel.

A method is named `NAME` or `NAME:PRESET` (for example `wskpn:s`). Each method module registers itself with
`register(MethodSpec(...))` when imported; `_load_all` imports them so the registry is complete.
"""

from __future__ import annotations

import copy
import importlib
import warnings
from dataclasses import dataclass
from typing import Callable

import torch

from model.io.frames import BUFFERS, RENDER_BUFFERS
from model.methods.base import FrameBatch, Method

METHOD_MODULES = (
    "model.methods.baselines",
    "model.methods.oidn",
    "model.methods.oidn_taa",
    "model.methods.fused",
    "model.methods.wskpn",
    "model.methods.afn",
    "model.methods.jnds",
    "model.methods.munet",
)


@dataclass(frozen=True)
class MethodSpec:
    name: str
    description: str
    factory: Callable[[str, int], Method]  # (preset, scale) -> method
    presets: tuple[str, ...] = ("default",)
    default_preset: str = "default"
    scales: tuple[int, ...] = (1,)
    learned: bool = False
    # The optional render buffers `step` reads (None: any of them). A stream client sends only the buffers a
    # session's method reads (method_buffers); tests check that a method's output does not change without the
    # optional buffers it does not declare.
    optional_buffers: tuple[str, ...] | None = None


OPTIONAL_RENDER_BUFFERS: tuple[str, ...] = tuple(name for name in RENDER_BUFFERS if not BUFFERS[name].required)


REGISTRY: dict[str, MethodSpec] = {}


def register(spec: MethodSpec) -> MethodSpec:
    if spec.default_preset not in spec.presets:
        raise ValueError(f"{spec.name}: default preset {spec.default_preset!r} is not among {spec.presets}")
    unknown = sorted(set(spec.optional_buffers or ()) - set(OPTIONAL_RENDER_BUFFERS))
    if unknown:
        raise ValueError(f"{spec.name}: {', '.join(unknown)} are not optional render buffers "
                         f"({', '.join(OPTIONAL_RENDER_BUFFERS)})")
    REGISTRY[spec.name] = spec
    return spec


def _load_all() -> None:
    for module in METHOD_MODULES:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as error:
            # Only a method module that does not exist yet is skipped; a missing dependency inside one is a bug.
            if error.name != module:
                raise


def parse_method_name(text: str) -> tuple[str, str | None]:
    name, _, preset = text.partition(":")
    if not name:
        raise ValueError(f"method name is empty in {text!r}; use NAME or NAME:PRESET")
    return name, preset or None


def method_spec(name: str) -> MethodSpec:
    _load_all()
    if name not in REGISTRY:
        raise KeyError(f"unknown method {name!r}; known methods: {', '.join(sorted(REGISTRY))}")
    return REGISTRY[name]


def method_buffers(name: str) -> tuple[str, ...]:
    """The render buffers method ``name`` reads, in the frame format's order: the required ones and the optional
    ones it declares (every optional one when it declares none); KeyError for an unknown method."""
    declared = method_spec(name).optional_buffers
    reads = set(OPTIONAL_RENDER_BUFFERS if declared is None else declared)
    return tuple(buffer for buffer in RENDER_BUFFERS if BUFFERS[buffer].required or buffer in reads)


def build_method(text: str, scale: int = 1) -> Method:
    """Construct `NAME[:PRESET]` at output `scale`, with clear errors for unknown names, presets, scales."""
    name, preset = parse_method_name(text)
    spec = method_spec(name)
    preset = preset or spec.default_preset
    if preset not in spec.presets:
        raise KeyError(f"method {name!r} has no preset {preset!r}; presets: {', '.join(spec.presets)}")
    if scale not in spec.scales:
        raise ValueError(f"method {name!r} does not run at scale {scale}; scales: "
                         f"{', '.join(str(s) for s in spec.scales)}")
    return spec.factory(preset, scale)


def all_methods() -> list[MethodSpec]:
    _load_all()
    return [REGISTRY[name] for name in sorted(REGISTRY)]


def example_batch(height: int = 32, width: int = 32, batch: int = 1, seed: int = 0,
                  device: torch.device | str = "cpu") -> FrameBatch:
    """A random but valid frame batch, for shapes, FLOP counting and smoke tests."""
    generator = torch.Generator().manual_seed(seed)

    def rand(channels: int) -> torch.Tensor:
        return torch.rand(batch, channels, height, width, generator=generator)

    normal = torch.nn.functional.normalize(rand(3) * 2 - 1, dim=1)
    return FrameBatch(color=rand(3) * 2, albedo=rand(3), normal=normal, depth=rand(1) + 1.0,
                      motion=(rand(2) - 0.5) * 2, jitter=torch.zeros(batch, 2),
                      camera_cut=torch.zeros(batch, dtype=torch.bool),
                      diffuse=rand(3), specular=rand(3), specular_albedo=rand(3) * 0.1,
                      roughness=rand(1)).to(device)


def inference_cost(method: Method, height: int = 32, width: int = 32) -> tuple[int, float]:
    """(parameters, FLOPs per output pixel) of the method as it runs: its ``for_inference()`` form (WSKPN's RepVGG
    blocks fused, int8 JNDS counted by its float32 twin), taken on a CPU copy so ``method`` is not changed.

    The one definition of a model's size: training tags, the fit ladder, ``denoiser methods``, evaluation reports
    and sessions all report this, so the same version never shows two sizes.
    """
    if not method.learned:
        return method.parameter_count(), float(flops_per_pixel(method, height, width))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an untrained int8 preset warns it has no activation ranges to convert
        runnable = copy.deepcopy(method).cpu().for_inference()
    return runnable.parameter_count(), float(flops_per_pixel(runnable, height, width))


def flops_per_pixel(method: Method, height: int = 32, width: int = 32) -> float:
    """FLOPs of one `step` with history, per output pixel, counted by torch's FLOP counter.

    Counts the tensor ops torch knows (convolutions, matmuls); element-wise ops and non-torch code (OIDN)
    are not counted, so this is a floor for learned methods and 0 for external ones.
    """
    from torch.utils.flop_counter import FlopCounterMode

    twin = getattr(method, "float_twin", lambda: None)()
    method = twin if twin is not None else method  # int8 kernels are invisible to the counter: count the float32 twin
    frame = example_batch(height, width)
    with torch.no_grad():
        _, state = method.step(frame, None)
        with FlopCounterMode(display=False) as counter:
            method.step(frame, state)
    return counter.get_total_flops() / (height * width * method.scale ** 2)
