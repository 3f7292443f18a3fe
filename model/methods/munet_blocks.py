"""Building blocks of MUNet (Kazmierczyk et al. 2025, seed paper 000): the multi-branch U-Net feature extractor
and the pieces of its filtering stage that are not shared ops.

The network (paper Sec. 3.3) runs a *radiance* branch for the noisy colour and a smaller *guiding* branch for the
noise-free guides side by side; in every layer the guiding features multiply the radiance branch's residual.
Outer layers use full 3x3 convolutions (:class:`MultiBranchLayer`, ``partial=False``), inner ones convolve half
the channels (:class:`PartialConv2d`, after FasterNet's PConv); three encoder and three decoder layers give the
three feature scales. ReLUs sit inside the residual units only: one after the downsampling and merge convolutions
left whole channels dead in the small presets. The filtering primitives (paper Sec. 3.4) are
:func:`affinity_kernel_logits`, :func:`partitioning_pyramid_filter` and :func:`sinusoidal_encoding`. In detail:
docs/methods.md, "model.methods.munet_blocks".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from model.ops.kernels import apply_pixel_kernels, kernel_offsets
from model.ops.pyramid import downsample2x, upsample2x

__all__ = [
    "sinusoidal_encoding",
    "PartialConv2d",
    "RadianceUnit",
    "GuideUnit",
    "MultiBranchLayer",
    "MUNetFeatureConfig",
    "MUNetFeatures",
    "affinity_kernel_logits",
    "partitioning_pyramid_filter",
    "pyramid_sizes",
    "LEVELS",
]

LEVELS = 3
"""Encoder/decoder layers of the U-Net, i.e. scales of the multi-scale features (paper: three)."""


# ---------------------------------------------------------------------------------------------------------------
# Encodings


def sinusoidal_encoding(value: torch.Tensor, channels: int, base: float) -> torch.Tensor:
    """Transformer sinusoidal embedding of a per-pixel scalar (N, 1, H, W) -> (N, channels, H, W).

    Channel 2i is ``sin(value / base^(2i / channels))`` and channel 2i+1 the matching cosine (Vaswani et al. 2017,
    with ``value`` in the role of the position). ``base`` sets the slowest period, ``2 pi base^(1 - 2/channels)``;
    it should exceed the largest value encoded so that the slowest pair stays monotone over the range.
    """
    if channels < 2 or channels % 2:
        raise ValueError(f"channels must be a positive even number, got {channels}")
    if value.dim() != 4 or value.shape[1] != 1:
        raise ValueError(f"value must be (N, 1, H, W), got {tuple(value.shape)}")
    exponents = torch.arange(0, channels, 2, dtype=value.dtype, device=value.device) / channels
    angles = value * base ** (-exponents).view(1, -1, 1, 1)  # (N, channels/2, H, W)
    return torch.stack([torch.sin(angles), torch.cos(angles)], dim=2).flatten(1, 2)


# ---------------------------------------------------------------------------------------------------------------
# Convolutional units


def _conv(in_channels: int, out_channels: int, kernel_size: int) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2)


class PartialConv2d(nn.Module):
    """Convolve the first ``conv_channels`` input channels and pass the rest through unchanged.

    Output = ``cat([conv(x[:, :conv_channels]), x[:, conv_channels:]])``, with as many channels as the input (the
    paper's partial convolution: "apply convolution to the portion of input features in a channel dimension (e.g.
    first half channels) and directly concatenate the features in remaining channels with the convolution output").
    """

    def __init__(self, channels: int, conv_channels: int, kernel_size: int = 3):
        super().__init__()
        if not 0 < conv_channels <= channels:
            raise ValueError(f"conv_channels must be in [1, {channels}], got {conv_channels}")
        self.conv_channels = conv_channels
        self.conv = _conv(conv_channels, conv_channels, kernel_size)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        head, tail = x[:, : self.conv_channels], x[:, self.conv_channels :]
        return torch.cat([self.conv(head), tail], dim=1)


def _residual_body(channels: int, partial: bool) -> nn.Sequential:
    """Residual path of a ConvRes unit: two 3x3 convolutions, or (partial) PConv 3x3 followed by a 1x1.

    The 1x1 after a partial convolution (FasterNet's PWConv) is what mixes the passed-through half back in; two
    partial convolutions in a row would leave that half untouched by any learned weight.
    """
    if partial:
        return nn.Sequential(PartialConv2d(channels, max(1, channels // 2), 3), nn.ReLU(inplace=True),
                             nn.Conv2d(channels, channels, 1))
    return nn.Sequential(_conv(channels, channels, 3), nn.ReLU(inplace=True), _conv(channels, channels, 3))


class RadianceUnit(nn.Module):
    """Radiance-branch ConvRes unit whose residual is multiplied by the guiding features: relu(x + body(x) * g)."""

    def __init__(self, channels: int, partial: bool):
        super().__init__()
        self.body = _residual_body(channels, partial)

    def forward(self, x: torch.Tensor, gate: torch.Tensor) -> torch.Tensor:
        return F.relu(x + self.body(x) * gate)


class GuideUnit(nn.Module):
    """Guiding-branch ConvRes unit: relu(g + body(g))."""

    def __init__(self, channels: int, partial: bool):
        super().__init__()
        self.body = _residual_body(channels, partial)

    def forward(self, g: torch.Tensor) -> torch.Tensor:
        return F.relu(g + self.body(g))


class MultiBranchLayer(nn.Module):
    """One MConvRes (``partial=False``) or MPConvRes (``partial=True``) layer of both branches.

    The guiding branch runs its (fewer) units first; its output, projected to the radiance width by a 1x1
    convolution when the widths differ, multiplies the residual of every radiance unit of the layer.
    Returns ``(radiance_features, guide_features)``.
    """

    def __init__(self, radiance_channels: int, guide_channels: int, radiance_units: int, guide_units: int,
                 partial: bool):
        super().__init__()
        if radiance_units < 1 or guide_units < 1:
            raise ValueError("a layer needs at least one radiance and one guide unit")
        self.guide = nn.ModuleList(GuideUnit(guide_channels, partial) for _ in range(guide_units))
        self.radiance = nn.ModuleList(RadianceUnit(radiance_channels, partial) for _ in range(radiance_units))
        self.gate = (nn.Identity() if guide_channels == radiance_channels
                     else nn.Conv2d(guide_channels, radiance_channels, 1))

    def forward(self, x: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        for unit in self.guide:
            g = unit(g)
        gate = self.gate(g)
        for unit in self.radiance:
            x = unit(x, gate)
        return x, g


class _Downsample(nn.Module):
    """2x2 convolution with stride 2 for both branches, linear: its inputs are ReLU outputs (non-negative), so a
    ReLU here would kill every channel whose weights start out mostly negative, for good; the residual units that
    follow bring the non-linearity."""

    def __init__(self, radiance_in: int, radiance_out: int, guide_in: int, guide_out: int):
        super().__init__()
        self.radiance = nn.Conv2d(radiance_in, radiance_out, 2, stride=2)
        self.guide = nn.Conv2d(guide_in, guide_out, 2, stride=2)

    def forward(self, x: torch.Tensor, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.radiance(x), self.guide(g)


class _SkipMerge(nn.Module):
    """2x nearest upsampling of the coarser decoder output, concatenated with the encoder skip, 1x1 conv (linear,
    for the reason given at :class:`_Downsample`)."""

    def __init__(self, radiance_coarse: int, radiance_skip: int, guide_coarse: int, guide_skip: int):
        super().__init__()
        self.radiance = nn.Conv2d(radiance_coarse + radiance_skip, radiance_skip, 1)
        self.guide = nn.Conv2d(guide_coarse + guide_skip, guide_skip, 1)

    def forward(self, x: torch.Tensor, g: torch.Tensor, x_skip: torch.Tensor,
                g_skip: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        size = (x_skip.shape[-2], x_skip.shape[-1])
        x = torch.cat([upsample2x(x, "nearest", size=size), x_skip], dim=1)
        g = torch.cat([upsample2x(g, "nearest", size=size), g_skip], dim=1)
        return self.radiance(x), self.guide(g)


# ---------------------------------------------------------------------------------------------------------------
# The feature extractor


@dataclass(frozen=True)
class MUNetFeatureConfig:
    """Widths of the two branches per level (finest first, three levels) and residual units per layer.

    The guiding branch is the smaller one (paper: "smaller number of ConvRes blocks and output features"), so
    ``guide_units <= radiance_units`` and its widths are at most the radiance widths.
    """

    radiance_widths: tuple[int, int, int]
    guide_widths: tuple[int, int, int]
    radiance_units: int
    guide_units: int

    def __post_init__(self) -> None:
        if len(self.radiance_widths) != LEVELS or len(self.guide_widths) != LEVELS:
            raise ValueError(f"MUNet has {LEVELS} levels; got widths {self.radiance_widths}, {self.guide_widths}")
        if min(self.radiance_widths + self.guide_widths) < 1:
            raise ValueError("widths must be positive")
        if not 1 <= self.guide_units <= self.radiance_units:
            raise ValueError("need 1 <= guide_units <= radiance_units (the guiding branch is the smaller one)")


class MUNetFeatures(nn.Module):
    """Multi-branch U-Net: (radiance input, guide input) at full size -> [(F_r^l, F_g^l) for l = 0, 1, 2].

    Level l features are at 1/2^(l+1) of the input size (the input layer already downsamples), so the input's
    height and width must be multiples of 2^LEVELS = 8 (the caller pads).
    """

    def __init__(self, config: MUNetFeatureConfig, radiance_in: int, guide_in: int):
        super().__init__()
        rw, gw = config.radiance_widths, config.guide_widths
        ru, gu = config.radiance_units, config.guide_units
        self.inputs = _Downsample(radiance_in, rw[0], guide_in, gw[0])
        self.downs = nn.ModuleList(_Downsample(rw[l - 1], rw[l], gw[l - 1], gw[l]) for l in range(1, LEVELS))
        # Full convolutions only in the outermost layers (encoder 0, decoder 0), partial everywhere inside.
        self.encoders = nn.ModuleList(MultiBranchLayer(rw[l], gw[l], ru, gu, partial=l > 0) for l in range(LEVELS))
        self.decoders = nn.ModuleList(MultiBranchLayer(rw[l], gw[l], ru, gu, partial=l > 0) for l in range(LEVELS))
        # merges[l] joins the level l+1 decoder output with the level l encoder skip.
        self.merges = nn.ModuleList(_SkipMerge(rw[l + 1], rw[l], gw[l + 1], gw[l]) for l in range(LEVELS - 1))

    def forward(self, radiance: torch.Tensor, guide: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        factor = 2 ** LEVELS
        if radiance.shape[-2] % factor or radiance.shape[-1] % factor:
            raise ValueError(f"input size {tuple(radiance.shape[-2:])} must be a multiple of {factor}")
        x, g = self.inputs(radiance, guide)
        skips = []
        for level, encoder in enumerate(self.encoders):
            if level:
                x, g = self.downs[level - 1](x, g)
            x, g = encoder(x, g)
            skips.append((x, g))
        features: list[tuple[torch.Tensor, torch.Tensor]] = [None] * LEVELS  # type: ignore[list-item]
        x, g = self.decoders[-1](x, g)
        features[-1] = (x, g)
        for level in range(LEVELS - 2, -1, -1):
            x, g = self.merges[level](x, g, *skips[level])
            x, g = self.decoders[level](x, g)
            features[level] = (x, g)
        return features


# ---------------------------------------------------------------------------------------------------------------
# Filtering primitives


def affinity_kernel_logits(features: torch.Tensor, bandwidth: torch.Tensor, confidence: torch.Tensor,
                           k: int = 3) -> torch.Tensor:
    """Per-pixel k x k kernel logits from feature vectors, in ``model.ops.kernels`` layout (N, k*k, H, W).

    ``logit_j(p) = -bandwidth(p) * ||features(p) - features(p + o_j)||^2 + confidence(p + o_j)``: softmax-normalized
    (``apply_pixel_kernels(..., normalize="softmax")``) this is a Gaussian in feature space, times a per-tap
    confidence. features (N, D, H, W); bandwidth (N, 1, H, W) >= 0; confidence (N, 1, H, W). Taps outside the
    image get finite logits here; ``apply_pixel_kernels`` drops them from the normalization.
    """
    n, _, h, w = features.shape
    if bandwidth.shape != (n, 1, h, w) or confidence.shape != (n, 1, h, w):
        raise ValueError("bandwidth and confidence must be (N, 1, H, W) like the features")
    r = k // 2
    padded = F.pad(torch.cat([features, confidence], dim=1), (r, r, r, r))
    logits = []
    for dx, dy in kernel_offsets(k):
        tap = padded[..., r + dy : r + dy + h, r + dx : r + dx + w]
        distance = (features - tap[:, :-1]).square().sum(dim=1, keepdim=True)
        logits.append(tap[:, -1:] - bandwidth * distance)
    return torch.cat(logits, dim=1)


def pyramid_sizes(size: tuple[int, int], levels: int) -> list[tuple[int, int]]:
    """Sizes of a ``build_pyramid`` of an image of ``size``: ceil halving, finest first."""
    sizes = [size]
    for _ in range(levels - 1):
        h, w = sizes[-1]
        sizes.append(((h + 1) // 2, (w + 1) // 2))
    return sizes


def partitioning_pyramid_filter(image: torch.Tensor, partitions: torch.Tensor,
                                kernel_logits: list[torch.Tensor], k: int = 3) -> torch.Tensor:
    """Partitioning-pyramid filtering (Balint et al. 2023) of ``image`` (N, C, H, W).

    partitions (N, L, H, W): per-pixel weights of the L levels (a partition of unity, e.g. a softmax).
    kernel_logits[l] (N, k*k, H_l, W_l): level l's kernels at the pyramid size of level l (ceil halving).
    Level l filters ``downsample2x^l(partitions[:, l] * image)`` with softmax-normalized kernels; the filtered
    levels are then combined coarse to fine, ``acc = upsample2x(acc, bilinear) + filtered_l``. Each level is a
    convex filter of its partition, so a constant image with constant partitions comes back unchanged, and
    non-negative inputs give non-negative outputs.
    """
    levels = partitions.shape[1]
    if len(kernel_logits) != levels:
        raise ValueError(f"{levels} partitions but {len(kernel_logits)} kernel levels")
    sizes = pyramid_sizes((image.shape[-2], image.shape[-1]), levels)
    filtered = []
    for level, (logits, size) in enumerate(zip(kernel_logits, sizes, strict=True)):
        part = partitions[:, level : level + 1] * image
        for _ in range(level):
            part = downsample2x(part)
        if tuple(logits.shape[-2:]) != size:
            raise ValueError(f"level {level} kernels must be {size}, got {tuple(logits.shape[-2:])}")
        filtered.append(apply_pixel_kernels(part, logits, k, normalize="softmax"))
    out = filtered[-1]
    for level in range(levels - 2, -1, -1):
        out = upsample2x(out, "bilinear", size=sizes[level]) + filtered[level]
    return out
