"""MUNet: joint denoising and upscaling with a multi-branch, multi-scale feature network (Kazmierczyk et al.
2025, seed paper 000). Scale 2 denoises a 1spp frame and upscales it 2x; scale 1 is the paper's denoise-only mode.

Per frame (paper Fig. 3, Sec. 3.2-3.4): the noisy colour and the guides are *unjittered* onto the target grid
(:func:`unjitter`) and the history is warped there; a two-branch U-Net (``model.methods.munet_blocks``: a radiance
and a guiding branch) gives three scales of features; from them, 3x3 feature-affinity kernels upscale-filter the
colour and the albedos, predicted weights accumulate both with their histories, and a partitioning pyramid
denoises the demodulated result, which is composed back and blended with the previous output. Renderers without
``specular_albedo`` or ``roughness`` get 0 and 1 for them. The steps, the choices the paper leaves open and the
loss: docs/methods.md, "model.methods.munet".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.history_rectification import RectifiableHistory
from model.methods.munet_blocks import (
    LEVELS,
    MUNetFeatureConfig,
    MUNetFeatures,
    affinity_kernel_logits,
    partitioning_pyramid_filter,
    pyramid_sizes,
    sinusoidal_encoding,
)
from model.methods.registry import MethodSpec, register
from model.ops.demodulate import demodulation_divisor
from model.ops.kernels import apply_pixel_kernels
from model.ops.pyramid import upsample2x
from model.ops.reproject import disocclusion_mask
from model.ops.tonemap import mulaw
from model.ops.warp import backward_warp, dilate_motion_by_depth, upscale_motion

__all__ = [
    "MUNet",
    "MUNetConfig",
    "MUNET_PRESETS",
    "unjitter",
    "sample_offsets",
    "update_sample_count",
    "reproject_history",
    "HISTORY_CHANNELS",
    "GEOMETRY_CHANNELS",
    "MAX_COUNT",
]

MAX_COUNT = 32.0
"""Cap of the accumulated sample count: keeps the encoded value inside the range training sequences cover."""
COUNT_CHANNELS = 8
COUNT_BASE = 1000.0  # slowest encoded period ~1100 samples, far above MAX_COUNT: that pair stays monotone
KERNEL = 3  # the paper's 3x3 Gaussian filters
PYRAMID_LEVELS = LEVELS + 1  # the target-resolution level plus one per feature scale
ALBEDO_LOSS_WEIGHT = 1.0  # paper: L_S = L_s^o + L_s^g, both weight 1

RADIANCE_INPUTS = 3 + 3 + 3 + COUNT_CHANNELS  # colour, history radiance, history output, count encoding
GUIDE_BUFFERS = 3 + 3 + 3 + 1  # diffuse albedo, specular albedo, normal, roughness
GUIDE_INPUTS = GUIDE_BUFFERS + 2 + 3 + 3 + COUNT_CHANNELS  # + sample offset, history albedos, count encoding

HISTORY_CHANNELS = {"radiance": 3, "albedo_up": 3, "specular_albedo_up": 3, "output": 3,
                    "count_radiance": 1, "count_albedo": 1}
"""The warped history, all at target resolution: accumulated radiance and albedos, the last output, the counts."""
GEOMETRY_CHANNELS = {"depth": 1, "normal": 3}
"""The rest of the state: the frame's unjittered target-resolution geometry, for the next frame's geometry test."""


@dataclass(frozen=True)
class MUNetConfig:
    """A preset: the feature extractor's shape and the length of the per-pixel feature vectors (kernels)."""

    features: MUNetFeatureConfig
    feature_dims: int

    def __post_init__(self) -> None:
        if self.feature_dims < 1:
            raise ValueError(f"feature_dims must be positive, got {self.feature_dims}")


MUNET_PRESETS: dict[str, MUNetConfig] = {
    "xs": MUNetConfig(MUNetFeatureConfig((8, 12, 16), (4, 6, 8), radiance_units=1, guide_units=1), 3),
    "s": MUNetConfig(MUNetFeatureConfig((16, 24, 32), (8, 12, 16), radiance_units=1, guide_units=1), 4),
    # Near the paper's 0.644 M parameters.
    "m": MUNetConfig(MUNetFeatureConfig((24, 64, 176), (16, 32, 64), radiance_units=2, guide_units=1), 8),
    "l": MUNetConfig(MUNetFeatureConfig((48, 96, 192), (24, 48, 64), radiance_units=2, guide_units=1), 8),
}
DEFAULT_PRESET = "s"


# ---------------------------------------------------------------------------------------------------------------
# Pre-processing


def unjitter(image: torch.Tensor, jitter: torch.Tensor, scale: int) -> torch.Tensor:
    """Resample a render-resolution buffer (N, C, H, W) onto the target grid (N, C, sH, sW), undoing the jitter.

    Render pixel x's sample lies at ``x + 0.5 + jitter`` (render pixels), i.e. at ``s (x + 0.5 + jitter)`` target
    pixels. Target pixel q takes the sample nearest its centre, render pixel ``floor((q + 0.5) / s - jitter)``:
    the nearest-neighbour upscale read ``s * jitter`` target pixels back (``backward_warp`` "nearest" with a
    constant offset; ``floor(floor(a) / s) = floor(a / s)`` makes the two equal). Edge pixels whose nearest
    sample would lie outside take the edge sample. Samples are never blended, so the noise stays per-sample
    and the aliased guides keep real values.
    """
    if scale not in (1, 2):
        raise ValueError(f"scale must be 1 or 2, got {scale}")
    upscaled = upsample2x(image, "nearest") if scale == 2 else image
    n, _, h, w = upscaled.shape
    still = torch.zeros((n, 2, h, w), dtype=image.dtype, device=image.device)
    shifted, _ = backward_warp(upscaled, still, mode="nearest", padding="border", jitter=-scale * jitter)
    return shifted


def sample_offsets(jitter: torch.Tensor, height: int, width: int, scale: int) -> torch.Tensor:
    """(N, 2, sH, sW): position of the sample each target pixel took (see :func:`unjitter`) minus the pixel's
    centre, in render pixels (x, y); within [-0.5, 0.5) away from the borders."""
    n = jitter.shape[0]
    xs = torch.arange(width, dtype=jitter.dtype, device=jitter.device) + 0.5
    ys = torch.arange(height, dtype=jitter.dtype, device=jitter.device) + 0.5
    grid = torch.stack(torch.meshgrid(xs, ys, indexing="xy"), dim=0).expand(n, 2, height, width)
    positions = unjitter(grid + jitter.view(n, 2, 1, 1), jitter, scale)
    txs = (torch.arange(width * scale, dtype=jitter.dtype, device=jitter.device) + 0.5) / scale
    tys = (torch.arange(height * scale, dtype=jitter.dtype, device=jitter.device) + 0.5) / scale
    centres = torch.stack(torch.meshgrid(txs, tys, indexing="xy"), dim=0).unsqueeze(0)
    return positions - centres


def update_sample_count(alpha: torch.Tensor, history_count: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Accumulated sample count after blending ``alpha * current + (1 - alpha) * history``.

    The count is blended like the signal, with 1 for the current frame and ``history_count + 1`` for the history
    (which gained this frame's sample): ``1 + (1 - alpha) * history_count``, capped at MAX_COUNT; 1 without valid
    history. alpha = 1 / (n + 1) (a running mean) gives about n + 1, alpha = 1 restarts at 1.
    """
    blended = (1.0 + (1.0 - alpha) * history_count).clamp_max(MAX_COUNT)
    return torch.where(valid, blended, torch.ones_like(blended))


def _split(x: torch.Tensor, layout: dict[str, int]) -> dict[str, torch.Tensor]:
    return dict(zip(layout, torch.split(x, list(layout.values()), dim=1), strict=True))


def reproject_history(frame: FrameBatch, state: State | None, scale: int, depth: torch.Tensor,
                      normal: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """The target-resolution history warped to this frame, masked to 0 where invalid, and the validity mask.

    depth (N, 1, sH, sW) and normal (N, 3, sH, sW) are this frame's unjittered geometry on the target grid.
    Motion is dilated 3x3 by nearest depth (foreground motion wins at silhouettes) and upscaled to target pixels
    (x scale). Target pixel q reads the previous output at ``centre(q) + scale * motion``, *without* the jitter:
    ``centre + jitter + motion`` is where the surface point of this frame's jittered *sample* was; MUNet's history
    and its unjittered inputs live at pixel centres, and the point at ``centre`` moved by (locally) the same
    motion, so it was at ``centre + motion``. Measured on data/bench (10 sequences, frames 1-5, warped scale-2
    reference against the next one): mean relative L1 0.026-0.18 without the jitter term against 0.030-0.33
    with ``+ jitter`` or ``- jitter`` (worst on the slow-moving dark_fireflies_s1: 0.063 against 0.33), and
    better on every sequence.

    Valid: inside the previous image, a non-zero sample count (a camera cut zeroes it) and the depth/normal
    test of ``model.ops.reproject.disocclusion_mask`` against the previous frame's geometry. The paper leaves all
    history rejection to its predicted weights; the geometry test is added because our CPU-length trainings
    did not learn to reject disoccluded history (600 steps of "s": a revealed dark wall kept the grey it
    replaced for 8 frames) while every baseline here rejects it by this rule. ``state=None`` gives all-zero
    history. Returns ``({name: (N, c, sH, sW)} for HISTORY_CHANNELS, valid (N, 1, sH, sW) bool)``.
    """
    n, _, h, w = depth.shape
    if state is None:
        empty = {name: depth.new_zeros((n, c, h, w)) for name, c in HISTORY_CHANNELS.items()}
        return empty, torch.zeros((n, 1, h, w), dtype=torch.bool, device=depth.device)
    motion = upscale_motion(dilate_motion_by_depth(frame.motion, frame.depth), scale).to(depth.dtype)
    stacked = torch.cat([state[name] for name in HISTORY_CHANNELS], dim=1)
    warped, inside = backward_warp(stacked, motion, mode="bilinear")
    history = _split(warped, HISTORY_CHANNELS)
    same_surface = disocclusion_mask(depth, normal, state["depth"], state["normal"], motion)
    valid = inside & (history["count_radiance"] > 0) & same_surface
    mask = valid.to(depth.dtype)
    return {name: value * mask for name, value in history.items()}, valid


@dataclass
class _TargetInputs:
    """The current frame on the target grid."""

    color: torch.Tensor  # linear HDR, (N, 3, sH, sW)
    albedo: torch.Tensor
    specular_albedo: torch.Tensor
    guides: torch.Tensor  # (N, GUIDE_BUFFERS, sH, sW): albedo, specular albedo, normal in [0, 1], roughness
    offsets: torch.Tensor  # (N, 2, sH, sW)
    depth: torch.Tensor  # (N, 1, sH, sW)
    normal: torch.Tensor  # (N, 3, sH, sW), world space


def _pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad the bottom and right so both sides are multiples of ``multiple`` (no copy when they are)."""
    h, w = x.shape[-2:]
    if h % multiple == 0 and w % multiple == 0:
        return x
    return F.pad(x, (0, -w % multiple, 0, -h % multiple), mode="replicate")


# ---------------------------------------------------------------------------------------------------------------
# Heads: 1x1 convolutions from features to filter parameters


def _kernel_layout(prefix: str, dims: int) -> dict[str, int]:
    return {f"{prefix}_features": dims, f"{prefix}_bandwidth": 1, f"{prefix}_confidence": 1}


class _Heads(nn.Module):
    """Per-pixel filter parameters from the multi-scale features.

    ``level[l]``: the denoising kernel of pyramid level l + 1 from (F_r^l, F_g^l). ``joint``: from (F_r^0, F_g^0),
    the target-resolution radiance upscaling kernel, the finest denoising kernel, alpha_r, the partition, the
    composition weights and omega. ``guide``: from F_g^0 alone (the paper derives the albedo filters from the
    guiding features), the albedo upscaling kernel and alpha_g. ``guide_projection``: target-resolution guides
    added to the three target-resolution feature vectors.
    """

    def __init__(self, config: MUNetConfig):
        super().__init__()
        rw, gw, d = config.features.radiance_widths, config.features.guide_widths, config.feature_dims
        self.dims = d
        self.joint_layout = {**_kernel_layout("up_radiance", d), **_kernel_layout("denoise", d), "alpha_radiance": 1,
                             "partitions": PYRAMID_LEVELS, "composition": 4, "omega": 1}
        self.guide_layout = {**_kernel_layout("up_albedo", d), "alpha_albedo": 1}
        self.level = nn.ModuleList(nn.Conv2d(rw[l] + gw[l], d + 2, 1) for l in range(LEVELS))
        self.joint = nn.Conv2d(rw[0] + gw[0], sum(self.joint_layout.values()), 1)
        self.guide = nn.Conv2d(gw[0], sum(self.guide_layout.values()), 1)
        self.guide_projection = nn.Conv2d(GUIDE_BUFFERS, 3 * d, 1)

    def target(self, finest: tuple[torch.Tensor, torch.Tensor], guides: torch.Tensor) -> dict[str, torch.Tensor]:
        """Target-resolution parameters: heads at the finest level, resized 2x and cropped to the guides' size."""
        radiance, guide = finest
        coarse = torch.cat([self.joint(torch.cat([radiance, guide], dim=1)), self.guide(guide)], dim=1)
        size = (guides.shape[-2], guides.shape[-1])
        resized = upsample2x(coarse, "bilinear")[..., : size[0], : size[1]]
        out = _split(resized, {**self.joint_layout, **self.guide_layout})
        projected = torch.split(self.guide_projection(guides), self.dims, dim=1)
        for name, extra in zip(("up_radiance", "denoise", "up_albedo"), projected, strict=True):
            out[f"{name}_features"] = out[f"{name}_features"] + extra
        return out

    def level_kernels(self, features: list[tuple[torch.Tensor, torch.Tensor]],
                      sizes: list[tuple[int, int]]) -> list[torch.Tensor]:
        """Kernel logits of pyramid levels 1..LEVELS, cropped from the padded feature maps to the pyramid sizes."""
        logits = []
        for head, (radiance, guide), (h, w) in zip(self.level, features, sizes, strict=True):
            out = _split(head(torch.cat([radiance, guide], dim=1))[..., :h, :w], _kernel_layout("k", self.dims))
            logits.append(_kernel_logits(out, "k"))
        return logits


def _kernel_logits(params: dict[str, torch.Tensor], prefix: str) -> torch.Tensor:
    return affinity_kernel_logits(params[f"{prefix}_features"], F.softplus(params[f"{prefix}_bandwidth"]),
                                  params[f"{prefix}_confidence"], KERNEL)


# ---------------------------------------------------------------------------------------------------------------
# The method


class MUNet(RectifiableHistory, Method):
    """Joint denoiser and upscaler; see the module docstring. State: ``HISTORY_CHANNELS`` and
    ``GEOMETRY_CHANNELS``, at target resolution.

    ``state["albedo_up"]`` / ``state["specular_albedo_up"]`` are the upscaled accumulated albedos, both the
    history of the next frame and what :meth:`auxiliary_loss` compares with the albedo references.
    """

    name = "munet"
    learned = True
    # Paper: alpha = 1 (spatial), beta = 1 (temporal) ramped up to 2 over training. The engine takes constants;
    # we keep beta's starting value, which is where our short CPU trainings spend their time.
    loss_weights = (1.0, 1.0)

    def __init__(self, preset: str = DEFAULT_PRESET, scale: int = 2):
        super().__init__(preset, scale)
        if preset not in MUNET_PRESETS:
            raise KeyError(f"munet has no preset {preset!r}; presets: {', '.join(MUNET_PRESETS)}")
        self.munet_config = MUNET_PRESETS[preset]
        self.features = MUNetFeatures(self.munet_config.features, RADIANCE_INPUTS, GUIDE_INPUTS)
        self.heads = _Heads(self.munet_config)
        self._init_rectification()

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        state = drop_history(state, frame)
        current = self._target_inputs(frame)
        history, valid = reproject_history(frame, state, self.scale, current.depth, current.normal)

        padded = [_pad_to_multiple(x, 2 ** LEVELS) for x in self._network_inputs(current, history)]
        features = self.features(*padded)
        params = self.heads.target(features[0], current.guides)
        sizes = pyramid_sizes((current.color.shape[-2], current.color.shape[-1]), PYRAMID_LEVELS)
        level_logits = self.heads.level_kernels(features, sizes[1:])

        # Upscaling filters and temporal accumulation of radiance and albedos.
        radiance = apply_pixel_kernels(current.color, _kernel_logits(params, "up_radiance"), KERNEL,
                                       normalize="softmax")
        albedos = apply_pixel_kernels(torch.cat([current.albedo, current.specular_albedo], dim=1),
                                      _kernel_logits(params, "up_albedo"), KERNEL, normalize="softmax")
        # rectify_history: the accumulated radiance clipped to this frame's upscaled samples before the blend
        history["radiance"] = self.rectified(history["radiance"], radiance)
        alpha_radiance = torch.sigmoid(params["alpha_radiance"])
        alpha_albedo = torch.sigmoid(params["alpha_albedo"])
        radiance = torch.where(valid, torch.lerp(history["radiance"], radiance, alpha_radiance), radiance)
        history_albedos = torch.cat([history["albedo_up"], history["specular_albedo_up"]], dim=1)
        albedos = torch.where(valid, torch.lerp(history_albedos, albedos, alpha_albedo), albedos)
        albedo, specular_albedo = albedos[:, :3], albedos[:, 3:]

        # Implicit decomposition: denoise radiance demodulated by each albedo, and as it is; recompose.
        diffuse_divisor = demodulation_divisor(albedo)
        specular_divisor = demodulation_divisor(specular_albedo)
        demodulated = torch.cat([radiance / diffuse_divisor, radiance / specular_divisor, radiance], dim=1)
        partitions = torch.softmax(params["partitions"], dim=1)
        denoised = partitioning_pyramid_filter(demodulated, partitions,
                                               [_kernel_logits(params, "denoise"), *level_logits], KERNEL)
        weights = torch.softmax(params["composition"], dim=1)
        composed = (weights[:, 0:1] * denoised[:, 0:3] * diffuse_divisor
                    + weights[:, 1:2] * denoised[:, 3:6] * specular_divisor
                    + weights[:, 2:3] * denoised[:, 6:9]
                    + weights[:, 3:4] * current.color)
        omega = torch.sigmoid(params["omega"])
        output = torch.where(valid, torch.lerp(composed, history["output"], omega), composed)

        new_state = {
            "radiance": radiance,
            "albedo_up": albedo,
            "specular_albedo_up": specular_albedo,
            "output": output,
            "count_radiance": update_sample_count(alpha_radiance, history["count_radiance"], valid),
            "count_albedo": update_sample_count(alpha_albedo, history["count_albedo"], valid),
            "depth": current.depth,
            "normal": current.normal,
        }
        return output, new_state

    def auxiliary_loss(self, frames: list[FrameBatch], states: list[State]) -> torch.Tensor | None:
        """Mean over frames of L1(upscaled albedo, reference) + L1(upscaled specular albedo, reference).

        References come from the optional ``reference_albedo`` / ``reference_specular_albedo`` fields ((N, 3, sH,
        sW), box-filtered at the target resolution); frames without ``reference_albedo`` add nothing, and without
        any the term is None.
        """
        terms = []
        for frame, state in zip(frames, states, strict=True):
            reference = getattr(frame, "reference_albedo", None)
            if reference is None:
                continue
            term = _l1(state["albedo_up"], reference, "reference_albedo")
            specular_reference = getattr(frame, "reference_specular_albedo", None)
            if specular_reference is not None:
                term = term + _l1(state["specular_albedo_up"], specular_reference, "reference_specular_albedo")
            terms.append(term)
        if not terms:
            return None
        return ALBEDO_LOSS_WEIGHT * torch.stack(terms).mean()

    # -- pre-processing -------------------------------------------------------------------------------------------

    def _target_inputs(self, frame: FrameBatch) -> _TargetInputs:
        s, jitter = self.scale, frame.jitter.to(frame.color.dtype)
        zeros = torch.zeros_like(frame.albedo)
        specular_albedo = frame.specular_albedo if frame.specular_albedo is not None else zeros
        roughness = frame.roughness if frame.roughness is not None else torch.ones_like(frame.depth)
        render = torch.cat([frame.color, frame.albedo, specular_albedo, frame.normal * 0.5 + 0.5, roughness,
                            frame.depth, frame.normal], dim=1)
        target = unjitter(render, jitter, s)
        return _TargetInputs(color=target[:, 0:3], albedo=target[:, 3:6], specular_albedo=target[:, 6:9],
                             guides=target[:, 3:13], offsets=sample_offsets(jitter, frame.height, frame.width, s),
                             depth=target[:, 13:14], normal=target[:, 14:17])

    @staticmethod
    def _network_inputs(current: _TargetInputs,
                        history: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        radiance = torch.cat([
            mulaw(current.color), mulaw(history["radiance"]), mulaw(history["output"]),
            sinusoidal_encoding(history["count_radiance"], COUNT_CHANNELS, COUNT_BASE),
        ], dim=1)
        guide = torch.cat([
            current.guides, current.offsets, history["albedo_up"], history["specular_albedo_up"],
            sinusoidal_encoding(history["count_albedo"], COUNT_CHANNELS, COUNT_BASE),
        ], dim=1)
        return radiance, guide


def _l1(prediction: torch.Tensor, reference: torch.Tensor, name: str) -> torch.Tensor:
    if reference.shape != prediction.shape:
        raise ValueError(f"{name} must have shape {tuple(prediction.shape)} (the output's), "
                         f"got {tuple(reference.shape)}")
    return (prediction - reference.to(prediction.dtype)).abs().mean()


register(MethodSpec(
    name="munet",
    description="MUNet (Kazmierczyk et al. 2025): multi-branch multi-scale U-Net, joint denoising and 2x "
                "upscaling with predicted temporal accumulation, implicit radiance decomposition and "
                "partitioning-pyramid kernels; scale 1 = denoise only",
    factory=lambda preset, scale: MUNet(preset, scale),
    presets=tuple(MUNET_PRESETS),
    default_preset=DEFAULT_PRESET,
    scales=(1, 2),
    optional_buffers=("specular_albedo", "roughness"),  # the second demodulated term; roughness is a guide
    learned=True,
))
