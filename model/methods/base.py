"""The one interface every method implements: `output, state = method.step(frame, state)`.

Training (unrolled over T frames), evaluation, benchmarks and inference sessions all drive methods through
`step`, one frame at a time, carrying `state` (the method's temporal history). `state=None` starts a
sequence. A camera cut is signalled per sample by `frame.camera_cut`: methods drop that sample's history
(see `drop_history`), so a batch may mix samples that continue with samples that restart. Every subclass's `step`
ends with the output bound of `model.ops.output_bound` (applied here, in `Method.__init_subclass__`).
"""

from __future__ import annotations

import abc
import functools
from dataclasses import dataclass, fields, replace
from typing import Any, Iterable

import numpy as np
import torch
from torch import nn

from model.io.frames import FrameBundle
from model.ops.output_bound import bound_output

State = dict[str, torch.Tensor]


@dataclass
class FrameBatch:
    """A batch of frames as NCHW float32 tensors on one device (see `model.io.frames` for the conventions).

    `reference` is the target at the method's output scale, and `reference_albedo` /
    `reference_specular_albedo` the box-filtered albedos at that resolution (for auxiliary losses such as
    an L1 on upscaled albedos); they are for losses and metrics only and a method's `step` never sees them
    (`without_reference`).
    """

    color: torch.Tensor  # (N, 3, H, W)
    albedo: torch.Tensor  # (N, 3, H, W)
    normal: torch.Tensor  # (N, 3, H, W)
    depth: torch.Tensor  # (N, 1, H, W)
    motion: torch.Tensor  # (N, 2, H, W) pixels; previous position = sample position + motion
    jitter: torch.Tensor  # (N, 2) sub-pixel offset of the sample from the pixel centre
    camera_cut: torch.Tensor  # (N,) bool: history must be dropped before this frame
    diffuse: torch.Tensor | None = None  # (N, 3, H, W)
    specular: torch.Tensor | None = None
    specular_albedo: torch.Tensor | None = None  # (N, 3, H, W)
    roughness: torch.Tensor | None = None  # (N, 1, H, W)
    reference: torch.Tensor | None = None  # (N, 3, H*s, W*s)
    reference_albedo: torch.Tensor | None = None  # (N, 3, H*s, W*s)
    reference_specular_albedo: torch.Tensor | None = None  # (N, 3, H*s, W*s)
    # A per-frame spatial denoiser's output at render resolution, precomputed: training caches OIDN's per stored
    # frame (model.training.spatial_cache) for methods built on it. Methods compute it themselves when it is None, which
    # is always the case in evaluation and sessions, so their timings include it.
    spatial_estimate: torch.Tensor | None = None  # (N, 3, H, W)

    @property
    def batch_size(self) -> int:
        return int(self.color.shape[0])

    @property
    def height(self) -> int:
        return int(self.color.shape[2])

    @property
    def width(self) -> int:
        return int(self.color.shape[3])

    @property
    def device(self) -> torch.device:
        return self.color.device

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    def to(self, device: torch.device | str) -> FrameBatch:
        return replace(self, **{name: t.to(device) for name, t in self.tensors().items()})

    def without_reference(self) -> FrameBatch:
        """The frame without any target-resolution buffer: what a method's `step` gets."""
        return replace(self, reference=None, reference_albedo=None, reference_specular_albedo=None)

    @classmethod
    def from_bundles(cls, bundles: Iterable[FrameBundle], scale: int | None = 1,
                     device: torch.device | str = "cpu") -> FrameBatch:
        """Stack frames of equal resolution; `scale` picks the reference (None: no reference).

        The albedo references at `scale` are filled when every frame has them, else left None.
        """
        bundles = list(bundles)
        if not bundles:
            raise ValueError("cannot build a FrameBatch from no frames")

        def stack(name: str, channels_last: bool = True) -> torch.Tensor | None:
            arrays = [getattr(b, name) for b in bundles]
            if any(a is None for a in arrays):
                return None
            array = np.stack(arrays)
            array = array[..., None] if array.ndim == 3 else array
            return torch.from_numpy(np.ascontiguousarray(array.transpose(0, 3, 1, 2))).float().to(device)

        def stack_target(arrays: list[np.ndarray | None]) -> torch.Tensor | None:
            if any(a is None for a in arrays):
                return None
            return torch.from_numpy(np.stack(arrays).transpose(0, 3, 1, 2)).float().contiguous().to(device)

        reference = reference_albedo = reference_specular_albedo = None
        if scale is not None:
            reference = stack_target([b.reference(scale) for b in bundles])
            reference_albedo = stack_target([b.reference_albedos.get(scale) for b in bundles])
            reference_specular_albedo = stack_target([b.reference_specular_albedos.get(scale) for b in bundles])
        return cls(color=stack("color"), albedo=stack("albedo"), normal=stack("normal"), depth=stack("depth"),
                   motion=stack("motion"),
                   jitter=torch.tensor([b.jitter for b in bundles], dtype=torch.float32, device=device),
                   camera_cut=torch.tensor([b.camera_cut for b in bundles], dtype=torch.bool, device=device),
                   diffuse=stack("diffuse"), specular=stack("specular"),
                   specular_albedo=stack("specular_albedo"), roughness=stack("roughness"), reference=reference,
                   reference_albedo=reference_albedo, reference_specular_albedo=reference_specular_albedo)


def drop_history(state: State | None, frame: FrameBatch) -> State | None:
    """Zero every state tensor for samples whose frame starts a new shot (`camera_cut`).

    Methods keep a per-pixel history sample count in their state; zeroed, it marks the history invalid.
    Returns None when every sample restarts, so a method can take its `state is None` path.
    """
    # Exported steps (model/deployment/export.py) take the state as an input: there a cut is the caller's, who passes zeros.
    if state is None or torch.compiler.is_exporting() or not bool(frame.camera_cut.any()):
        return state
    if bool(frame.camera_cut.all()):
        return None
    keep = (~frame.camera_cut).to(frame.color.dtype)
    return {name: value * keep.view(-1, *([1] * (value.dim() - 1))).to(value.dtype) for name, value in state.items()}


class Method(nn.Module, abc.ABC):
    """Base class of every method, learned or not.

    Subclasses set `name`, `preset`, `scale` (output resolution / render resolution) and implement `step`.
    Learned methods are trained through `step` too; `learned` is False for filters without parameters.
    """

    name: str = "method"
    learned: bool = False
    #: True when the network works at render resolution only and the output is upscaled by interpolation, so
    #: its weights do not depend on `scale` (a 1x checkpoint runs at 2x as "method + bicubic").
    denoises_at_render_resolution: bool = False
    #: OIDN quality of the spatial estimate the method starts every frame from (None: it uses none). Training
    #: precomputes it per stored frame and passes it as ``FrameBatch.spatial_estimate``.
    spatial_prior: str | None = None
    #: (spatial, temporal) loss weights the training engine uses unless the user sets them.
    loss_weights: tuple[float, float] = (1.0, 0.25)

    def __init_subclass__(cls, **kwargs: Any) -> None:
        # Every subclass's own `step` ends with the output bound (model/ops/output_bound.py), in this one place,
        # so no method, however its network behaves, returns radiance its inputs cannot explain or a NaN.
        super().__init_subclass__(**kwargs)
        step = cls.__dict__.get("step")
        if step is not None and not getattr(step, "bounds_output", False):
            cls.step = _bounded_step(step)

    def __init__(self, preset: str = "default", scale: int = 1):
        super().__init__()
        if scale not in (1, 2):
            raise ValueError(f"{self.name}: scale must be 1 or 2, got {scale}")
        self.preset = preset
        self.scale = scale

    @property
    def label(self) -> str:
        return f"{self.name}:{self.preset}" if self.preset != "default" else self.name

    @abc.abstractmethod
    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        """Denoise (and upscale by `scale`) one frame; returns (N, 3, H*scale, W*scale) radiance and new state."""

    def network_input_dtype(self) -> torch.dtype:
        """The dtype the method's networks read their input in on this thread: float32, unless an inference form
        (``model.deployment.inference_forms``) runs them in bfloat16, where an input made in it saves their cast."""
        return torch.float32

    def auxiliary_loss(self, frames: list[FrameBatch], states: list[State]) -> torch.Tensor | None:
        """Method-specific training terms beyond the engine's spatial + temporal loss (e.g. an albedo L1).

        `frames` are the unrolled training frames with their references; `states[t]` is the state `step`
        returned for frame t. None means no extra term.
        """
        return None

    def load_initial_weights(self, state_dict: dict[str, torch.Tensor]) -> None:
        """Take another checkpoint's weights as the start of a new training run (``--init-from``).

        The same architecture by default; methods whose variants share weights (JNDS float32 -> int8 QAT)
        accept the other variant's state dict too.
        """
        self.load_state_dict(state_dict)

    def use_shipped_settings(self) -> None:
        """Take the run-time settings the family's shipped models run (a training from nothing starts with them,
        ``TrainingSettings.shipped_settings``). Most families have none; the fused family's are its stale-history
        tests, sample mean and texture detail."""

    def run_time_settings(self) -> dict[str, Any]:
        """The settings this model runs that are no weights (name -> value; training logs them to MLflow)."""
        return {}

    def for_inference(self) -> Method:
        """This method in its fast inference form (eval mode; subclasses fuse layers): sessions, benchmarks
        and evaluation run this, training runs the method as built. Outputs must match the training form."""
        return self.eval()

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def config(self) -> dict[str, Any]:
        """What reconstructs this method: registry name, preset, scale (checkpoints store it)."""
        return {"method": self.name, "preset": self.preset, "scale": self.scale}


def _bounded_step(step):
    @functools.wraps(step)
    def bounded(self: Method, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        output, new_state = step(self, frame, state)
        return bound_output(output, frame.color), new_state

    bounded.bounds_output = True
    return bounded


def unbounded_step(method: Method, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
    """``method.step`` without the output bound: for measuring what the bound changes, never for serving."""
    step = type(method).step
    return getattr(step, "__wrapped__", step)(method, frame, state)


def inference_outputs(method: Method, frames: Iterable[FrameBundle], inference_forms="measured") -> list[np.ndarray]:
    """The method's inference form (its networks in the measured form of ``model.deployment.inference_forms``, as sessions
    run them) stepped over ``frames`` from a new history, outputs as (H, W, 3) arrays: what a session on this
    method must answer for the same frames, to compare a server's outputs against."""
    from model.deployment.inference_forms import load_form_table, with_inference_forms

    method = with_inference_forms(method.for_inference(), load_form_table(inference_forms))
    outputs, state = [], None
    with torch.no_grad():
        for frame in frames:
            output, state = method.step(FrameBatch.from_bundles([frame], scale=None), state)
            outputs.append(output[0].permute(1, 2, 0).numpy().copy())
    return outputs
