"""AFN: real-time Monte Carlo denoising with an adaptive fusion network (Lee et al. 2024, seed paper 004).

Per frame, on albedo-demodulated radiance (paper Sec. III): the previous accumulated radiance is warped and blended
with the new 1spp sample where the depth/normal test passes (``r_TA``); one light-weight U-Net reads the raw frame and
``r_TA`` with the guides and predicts k x k kernels for the raw frame at half resolution, kernels for ``r_TA`` at full
resolution and a fusion weight ``alpha``; the scale compositor ``i = d_TA - alpha U(D(d_TA)) + alpha U(d_1spp)`` swaps
the accumulated frame's low frequencies for the current frame's where ``alpha`` says the history is stale; a few
convolutions refine ``i`` with a residual, and the output is remodulated with the albedo. The paper gives no channel
widths: "m" is the paper-like point (k = 7), "xs"/"s" cheaper, "l" deeper and wider. At scale 2 it denoises at
render resolution and upscales bicubically ("AFN + bicubic"). The steps with the paper's equations: docs/methods.md,
"model.methods.afn".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from model.methods.baselines import bicubic_upscale
from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.history_rectification import RectifiableHistory
from model.methods.registry import MethodSpec, register
from model.ops.accumulate import accumulate
from model.ops.kernels import apply_pixel_kernels
from model.ops.pyramid import downsample2x, upsample2x
from model.ops.rectify import rectify_accumulated
from model.ops.reproject import reproject_history
from model.ops.tonemap import log_tonemap, log_tonemap_inverse
from model.ops.demodulate import demodulate

__all__ = ["AFN", "AFNConfig", "AFN_PRESETS", "scale_composite", "temporal_accumulate"]

# TA blend floor, the value BMFR/NBGD/WSKPN use for their accumulation preprocessing.
TA_ALPHA_MIN = 0.2
# The count stops at 1 / TA_ALPHA_MIN: from there on the blend is a fixed-rate EMA, so larger counts carry no
# information, and capping keeps the count guide in the range short training sequences already cover.
TA_MAX_COUNT = 1.0 / TA_ALPHA_MIN
# The refinement residual lives in log(1 + x) space; clamping it keeps expm1 finite for any weights.
MAX_LOG_RADIANCE = 20.0
GUIDE_CHANNELS = 8  # albedo 3, normal 3, depth 1, 1/count 1


@dataclass(frozen=True)
class AFNConfig:
    """Size of one AFN preset.

    widths: U-Net channels per level, full resolution first; level 1 (half scale) must exist because the 1spp
        kernels are predicted there, so at least two levels.
    encoder_convs: 3x3 convolutions per encoder level.
    kernel_size: k of the k x k per-pixel kernels (the paper uses 7).
    refine_width, refine_layers: the refinement module's channels and number of 3x3 convolutions.
    """

    widths: tuple[int, ...]
    encoder_convs: int
    kernel_size: int
    refine_width: int
    refine_layers: int

    def __post_init__(self) -> None:
        if len(self.widths) < 2:
            raise ValueError(f"AFN needs at least two U-Net levels (full and half scale), got widths {self.widths}")
        if self.kernel_size < 1 or self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be a positive odd integer, got {self.kernel_size}")
        if self.encoder_convs < 1 or self.refine_layers < 2:
            raise ValueError("AFN needs encoder_convs >= 1 and refine_layers >= 2")


AFN_PRESETS: dict[str, AFNConfig] = {
    "xs": AFNConfig(widths=(8, 16), encoder_convs=1, kernel_size=5, refine_width=8, refine_layers=2),
    "s": AFNConfig(widths=(12, 24, 32), encoder_convs=1, kernel_size=7, refine_width=12, refine_layers=2),
    "m": AFNConfig(widths=(12, 24, 32), encoder_convs=2, kernel_size=7, refine_width=16, refine_layers=3),
    "l": AFNConfig(widths=(16, 32, 48, 64), encoder_convs=2, kernel_size=7, refine_width=24, refine_layers=4),
}


# ---------------------------------------------------------------------------------------------------------------
# Pre-processing: demodulation, guides, temporal accumulation


def guide_features(frame: FrameBatch, count: torch.Tensor) -> torch.Tensor:
    """(N, 8, H, W) auxiliary features in [0, 1]: albedo, normal, depth, 1 / sample count.

    Normal and depth are scaled linearly to [0, 1] (paper Sec. III-A): normal by (n + 1) / 2, depth by each
    sample's own maximum (per sample, so a batch gives the same answer as its samples run one by one).
    """
    depth = frame.depth
    depth_max = depth.amax(dim=(1, 2, 3), keepdim=True).clamp_min(1e-6)
    return torch.cat([frame.albedo, frame.normal * 0.5 + 0.5, depth / depth_max, 1.0 / count], dim=1)


def temporal_accumulate(
    radiance: torch.Tensor, frame: FrameBatch, state: State | None, rectify: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """Blend demodulated ``radiance`` (N, 3, H, W) with the reprojected history; returns ``(r_TA, count)``. With
    ``rectify`` the history is first clipped to ``radiance``'s neighbourhood (``rectify_accumulated``).

    Reprojection (bilinear history, nearest count, depth/normal test, camera cuts) is
    ``model.ops.reproject.reproject_history``.
    """
    if state is None:
        return accumulate(radiance, None, None, None, alpha_min=TA_ALPHA_MIN)
    history, count, valid = reproject_history(state["accumulated"], state["count"], frame.depth, frame.normal,
                                              state["depth"], state["normal"], frame.motion, frame.jitter,
                                              state["jitter"])
    if rectify:
        history = rectify_accumulated(history, radiance)
    return accumulate(radiance, history, count, valid,
                      alpha_min=TA_ALPHA_MIN, max_count=TA_MAX_COUNT)


# ---------------------------------------------------------------------------------------------------------------
# Filtering and fusion


def scale_composite(fine: torch.Tensor, coarse: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """The scale compositor (paper Eq. 3, after Vogels et al. 2018): ``fine - a U(D(fine)) + a U(coarse)``.

    fine (N, C, H, W) is the filtered accumulated frame d_TA, coarse (N, C, ceil(H/2), ceil(W/2)) the 1spp frame
    filtered at half scale d_1spp, alpha (N, 1, H, W) the per-pixel fusion weight. D is 2x2 average pooling and
    U nearest-neighbour upsampling (cropped back to H x W for odd sizes), so a = 0 keeps d_TA and a = 1 replaces
    its 2x2 block means by d_1spp while keeping its within-block detail.
    """
    size = (fine.shape[-2], fine.shape[-1])
    expected = ((size[0] + 1) // 2, (size[1] + 1) // 2)
    if tuple(coarse.shape[-2:]) != expected:
        raise ValueError(f"coarse must be {expected} for a {size} fine image, got {tuple(coarse.shape[-2:])}")
    fine_low = upsample2x(downsample2x(fine), mode="nearest", size=size)
    return fine + alpha * (upsample2x(coarse, mode="nearest", size=size) - fine_low)


# ---------------------------------------------------------------------------------------------------------------
# Networks


def _conv(in_channels: int, out_channels: int, kernel: int = 3) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, kernel, padding=kernel // 2)


class KernelPredictor(nn.Module):
    """The multi-scale kernel prediction network M (paper Eq. 1): a light-weight U-Net.

    Input: tone-mapped r_1spp and r_TA (3 + 3) and the guides. Outputs, read out of the decoder at two scales
    ("slicing feature maps of two different scales of the decoder"): K_1spp logits (N, k*k, H/2, W/2) from the
    half-scale decoder features, K_TA logits (N, k*k, H, W) and the fusion weight alpha (N, 1, H, W) from the
    full-scale ones. The read-outs are 1x1 convolutions so the k*k = 49 kernel channels never pass through a 3x3
    layer; that keeps the cost of the (expensive, full-resolution) kernel maps at a few FLOPs per channel.
    """

    def __init__(self, config: AFNConfig, in_channels: int):
        super().__init__()
        widths = config.widths
        taps = config.kernel_size ** 2
        self.encoder = nn.ModuleList()
        previous = in_channels
        for width in widths:
            layers: list[nn.Module] = []
            for i in range(config.encoder_convs):
                layers += [_conv(previous if i == 0 else width, width), nn.ReLU(inplace=True)]
            self.encoder.append(nn.Sequential(*layers))
            previous = width
        # decoder[l] merges the upsampled level l+1 features with the level-l skip; index 0 is full resolution.
        self.decoder = nn.ModuleList(
            nn.Sequential(_conv(widths[level + 1] + widths[level], widths[level]), nn.ReLU(inplace=True))
            for level in range(len(widths) - 1)
        )
        self.head_1spp = nn.Conv2d(widths[1], taps, 1)
        self.head_ta = nn.Conv2d(widths[0], taps + 1, 1)  # K_TA logits and the alpha logit

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        skips = []
        for level, block in enumerate(self.encoder):
            x = block(x if level == 0 else downsample2x(x))
            skips.append(x)
        decoded = {len(skips) - 1: x}  # decoder output per level; the deepest level is the bottleneck itself
        for level in range(len(skips) - 2, -1, -1):
            skip = skips[level]
            x = upsample2x(x, mode="bilinear", size=(skip.shape[-2], skip.shape[-1]))
            x = self.decoder[level](torch.cat([x, skip], dim=1))
            decoded[level] = x
        kernels_1spp = self.head_1spp(decoded[1])
        out = self.head_ta(decoded[0])
        return kernels_1spp, out[:, :-1], torch.sigmoid(out[:, -1:])


class Refinement(nn.Module):
    """The refinement module R (paper Eq. 4): 3x3 convolutions predicting a residual for the fused image.

    It reads log(1 + i) and the guides and adds its residual in that log space, ``o = exp(log(1 + i) + R) - 1``:
    there the residual is a relative correction (scale-invariant, like the SMAPE loss), and clamping the sum at 0
    keeps the radiance non-negative without squashing the network's output.
    """

    def __init__(self, config: AFNConfig, in_channels: int):
        super().__init__()
        layers: list[nn.Module] = []
        previous = in_channels
        for _ in range(config.refine_layers - 1):
            layers += [_conv(previous, config.refine_width), nn.ReLU(inplace=True)]
            previous = config.refine_width
        last = _conv(previous, 3)
        # Start close to the identity (output = fused image) but not at it: zero weights would also zero the
        # gradients of every earlier refinement layer at the first step.
        with torch.no_grad():
            last.weight.mul_(0.1)
            last.bias.zero_()
        layers.append(last)
        self.body = nn.Sequential(*layers)

    def forward(self, fused: torch.Tensor, guides: torch.Tensor) -> torch.Tensor:
        log_fused = log_tonemap(fused)
        residual = self.body(torch.cat([log_fused, guides], dim=1))
        return log_tonemap_inverse((log_fused + residual).clamp(0.0, MAX_LOG_RADIANCE))


# ---------------------------------------------------------------------------------------------------------------
# The method


class AFN(RectifiableHistory, Method):
    """Adaptive fusion network. State: accumulated demodulated radiance, its count, and the frame's depth/normal
    (for the next frame's geometry test); none of it depends on the parameters, so it carries no gradient."""

    name = "afn"
    learned = True
    denoises_at_render_resolution = True

    def __init__(self, preset: str = "m", scale: int = 1):
        super().__init__(preset, scale)
        if preset not in AFN_PRESETS:
            raise KeyError(f"afn has no preset {preset!r}; presets: {', '.join(AFN_PRESETS)}")
        self.afn_config = AFN_PRESETS[preset]
        self.kernel_size = self.afn_config.kernel_size
        self.predictor = KernelPredictor(self.afn_config, in_channels=6 + GUIDE_CHANNELS)
        self.refinement = Refinement(self.afn_config, in_channels=3 + GUIDE_CHANNELS)
        self._init_rectification()

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        state = drop_history(state, frame)
        radiance, divisor = demodulate(frame.color, frame.albedo)
        with torch.no_grad():  # TA has no parameters; keeping it out of the graph saves memory when unrolling
            accumulated, count = temporal_accumulate(radiance, frame, state, self.rectify_history)
        guides = guide_features(frame, count)

        network_input = torch.cat([log_tonemap(radiance), log_tonemap(accumulated), guides], dim=1)
        kernels_1spp, kernels_ta, alpha = self.predictor(network_input)

        # Filter linear HDR radiance (paper: "to retain the original HDR distribution"); softmax-normalized
        # kernels are convex combinations, so both results stay non-negative.
        k = self.kernel_size
        filtered_1spp = apply_pixel_kernels(downsample2x(radiance), kernels_1spp, k, normalize="softmax")
        filtered_ta = apply_pixel_kernels(accumulated, kernels_ta, k, normalize="softmax")
        # The compositor subtracts a block mean, so a pixel darker than its block can go slightly negative.
        fused = scale_composite(filtered_ta, filtered_1spp, alpha).clamp_min(0.0)

        output = self.refinement(fused, guides) * divisor
        output = bicubic_upscale(output, self.scale)
        new_state = {"accumulated": accumulated, "count": count,
                     "depth": frame.depth.detach(), "normal": frame.normal.detach(), "jitter": frame.jitter.detach()}
        return output, new_state


register(MethodSpec(
    name="afn",
    description="Adaptive fusion network (Lee et al. 2024): kernels for the 1spp frame at half scale and the "
                "accumulated frame, scale-compositor fusion, residual refinement",
    factory=lambda preset, scale: AFN(preset, scale),
    presets=tuple(AFN_PRESETS),
    default_preset="m",
    scales=(1, 2),
    optional_buffers=(),
    learned=True,
))
