"""WSKPN: real-time denoising with a weight-sharing kernel prediction network (Fan et al. 2021, seed paper 002).

Per frame (paper figure 1): the noisy radiance is demodulated by the diffuse albedo and accumulated over time where
the depth + normal test passes (BMFR's preprocessing, blend 0.2); the ImportanceNet, a stack of RepVGG blocks,
predicts per pixel one importance and one fusion logit per kernel size (3, 5, ..., 13); each importance map defines
a weight-sharing kernel on the accumulated irradiance, the six results are blended by the fusion softmax
(``model.ops.splat.weight_sharing_fused``) and remodulated; at scale 2 the result is upscaled bicubically. The
network reads log(1 + irradiance), not the paper's gamma-corrected LDR colour, so bright pixels and fireflies stay
apart. Presets "s" and "m" are the paper's ImportanceNets, "xs" and "l" U-Nets of RepVGG blocks; call
:meth:`WSKPN.reparameterize` before inference. The steps, the inputs and the presets in detail: docs/methods.md,
"model.methods.wskpn".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.baselines import bicubic_upscale
from model.methods.history_rectification import RectifiableHistory
from model.methods.registry import MethodSpec, register
from model.methods.repvgg import RepVGGBlock, reparameterize
from model.ops.accumulate import accumulate
from model.ops.demodulate import demodulation_divisor
from model.ops.pyramid import downsample2x, upsample2x
from model.ops.reproject import reproject_history
from model.ops.splat import WSKPN_SIZES, weight_sharing_fused
from model.ops.tonemap import log_tonemap

__all__ = [
    "ImportanceNetConfig",
    "ImportanceNet",
    "PRESETS",
    "WSKPN",
    "INPUT_CHANNELS",
]

ACCUMULATION_ALPHA = 0.2
"""Weight of the new frame once the history is full (BMFR's blend factor, 1/5)."""
MAX_COUNT = 1.0 / ACCUMULATION_ALPHA
"""Counts stop at the point where the running mean turns into the exponential average; also the input scale."""

INPUT_CHANNELS = 3 + 3 + 3 + 1 + 1  # log irradiance, albedo, normal, depth, count


@dataclass(frozen=True)
class ImportanceNetConfig:
    """Shape of the ImportanceNet.

    widths: channels per resolution level, finest first; one entry is a plain full-resolution stack (the paper's
    nets), more entries a U-Net with a 2x downsampling between levels. blocks: RepVGG blocks per level on the way
    down (and per level on the way up). kernel_size: largest RepVGG branch (the paper's blocks: 5).
    The output block (linear, it produces logits) comes on top, so a plain net has ``blocks + 1`` layers.
    """

    widths: tuple[int, ...]
    blocks: int
    kernel_size: int

    def __post_init__(self) -> None:
        if not self.widths or min(self.widths) < 1:
            raise ValueError(f"widths must be positive channel counts, got {self.widths}")
        if self.blocks < 1:
            raise ValueError(f"blocks must be >= 1, got {self.blocks}")


PRESETS: dict[str, ImportanceNetConfig] = {
    "xs": ImportanceNetConfig(widths=(8, 16), blocks=1, kernel_size=3),
    "s": ImportanceNetConfig(widths=(14,), blocks=2, kernel_size=5),  # paper "3-layer" (ImportanceNet-2)
    "m": ImportanceNetConfig(widths=(14,), blocks=5, kernel_size=5),  # paper "6-layer" (ImportanceNet-1)
    "l": ImportanceNetConfig(widths=(24, 32, 48), blocks=2, kernel_size=3),
}
DEFAULT_PRESET = "s"


def _stage(in_channels: int, out_channels: int, blocks: int, kernel_size: int) -> nn.Sequential:
    layers = [RepVGGBlock(in_channels, out_channels, kernel_size)]
    layers += [RepVGGBlock(out_channels, out_channels, kernel_size) for _ in range(blocks - 1)]
    return nn.Sequential(*layers)


class ImportanceNet(nn.Module):
    """RepVGG encoder(-decoder): features (N, C_in, H, W) -> logits (N, C_out, H, W)."""

    def __init__(self, in_channels: int, out_channels: int, config: ImportanceNetConfig):
        super().__init__()
        widths, k = config.widths, config.kernel_size
        self.encoders = nn.ModuleList()
        channels = in_channels
        for width in widths:
            self.encoders.append(_stage(channels, width, config.blocks, k))
            channels = width
        # decoders[i] merges level (L-2-i) with the upsampled level below it, coarsest merge first.
        self.decoders = nn.ModuleList(
            _stage(widths[level] + widths[level + 1], widths[level], config.blocks, k)
            for level in reversed(range(len(widths) - 1))
        )
        self.head = RepVGGBlock(widths[0], out_channels, k, activation=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        skips = []
        for level, encoder in enumerate(self.encoders):
            x = encoder(downsample2x(x) if level else x)
            skips.append(x)
        for decoder, skip in zip(self.decoders, reversed(skips[:-1])):
            x = decoder(torch.cat([upsample2x(x, size=tuple(skip.shape[-2:])), skip], dim=1))
        return self.head(x)


class WSKPN(RectifiableHistory, Method):
    """Weight-sharing kernel prediction denoiser; state holds the accumulated irradiance and last geometry.

    State tensors: ``irradiance`` (N, 3, H, W) accumulated demodulated radiance, ``count`` (N, 1, H, W) its
    sample count (0 after a cut marks it invalid), ``depth`` (N, 1, H, W) and ``normal`` (N, 3, H, W) of the
    frame it belongs to, for the geometry test.
    """

    name = "wskpn"
    learned = True
    denoises_at_render_resolution = True

    def __init__(self, preset: str = DEFAULT_PRESET, scale: int = 1):
        super().__init__(preset, scale)
        if preset not in PRESETS:
            raise KeyError(f"wskpn has no preset {preset!r}; presets: {', '.join(PRESETS)}")
        self.sizes = WSKPN_SIZES
        self.importance_net = ImportanceNet(INPUT_CHANNELS, 2 * len(self.sizes), PRESETS[preset])
        self._init_rectification()

    def reparameterize(self) -> WSKPN:
        """Fuse every RepVGG block into one convolution (in place) for inference; returns self."""
        reparameterize(self.importance_net)
        return self

    def for_inference(self) -> WSKPN:
        return self.eval().reparameterize()

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        state = drop_history(state, frame)
        divisor = demodulation_divisor(frame.albedo)
        irradiance, count = self._accumulate(frame.color / divisor, frame, state)
        logits = self.importance_net(self._network_inputs(irradiance, count, frame))
        m = len(self.sizes)
        filtered = weight_sharing_fused(irradiance, logits[:, :m], logits[:, m:], self.sizes)
        output = bicubic_upscale(filtered * divisor, self.scale)
        new_state = {"irradiance": irradiance, "count": count, "depth": frame.depth, "normal": frame.normal,
                     "jitter": frame.jitter}
        return output, new_state

    def _accumulate(
        self, irradiance: torch.Tensor, frame: FrameBatch, state: State | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        if state is None:
            return accumulate(irradiance, None, None, None, alpha_min=ACCUMULATION_ALPHA)
        history, count, valid = reproject_history(
            state["irradiance"], state["count"], frame.depth, frame.normal, state["depth"], state["normal"],
            frame.motion, frame.jitter, state["jitter"]
        )
        return accumulate(irradiance, self.rectified(history, irradiance), count, valid, alpha_min=ACCUMULATION_ALPHA,
                          max_count=MAX_COUNT)

    @staticmethod
    def _network_inputs(irradiance: torch.Tensor, count: torch.Tensor, frame: FrameBatch) -> torch.Tensor:
        depth_max = frame.depth.amax(dim=(1, 2, 3), keepdim=True).clamp_min(torch.finfo(frame.depth.dtype).tiny)
        return torch.cat(
            [
                log_tonemap(irradiance),
                frame.albedo,
                (frame.normal + 1.0) * 0.5,  # the paper scales normals linearly to [0, 1]
                frame.depth / depth_max,
                count / MAX_COUNT,
            ],
            dim=1,
        )


register(
    MethodSpec(
        name="wskpn",
        description="weight-sharing kernel prediction (Fan et al. 2021): RepVGG ImportanceNet, kernels 3..13 "
        "fused, on temporally accumulated demodulated irradiance; scale 2 = WSKPN + bicubic",
        factory=lambda preset, scale: WSKPN(preset, scale),
        presets=tuple(PRESETS),
        default_preset=DEFAULT_PRESET,
        scales=(1, 2),
        optional_buffers=(),
        learned=True,
    )
)
