"""JNDS: joint neural denoising and supersampling (seed paper 001), with an int8 variant.

One frame, render resolution H x W in, target resolution sH x sW out (s = 1 or 2), after the paper's Fig. 3: an
input block on the noisy lobes (diffuse demodulated by the albedo, specular), the guides and the warped history; a
U-Net at half resolution whose levels predict filter kernels; parameter-free spatiotemporal filter paths for the
diffuse and the specular lobe; the composite ``albedo * diffuse + specular``; and an upsample block that predicts,
per target pixel, kernels for the composite and the warped previous output and the blend weight between them.
Histories are read at ``centre + motion`` (the jitter is an input, not a warp offset); as in the paper there is no
geometric disocclusion test. Presets ending in ``-int8`` are the same network prepared for quantization-aware
training (``model.methods.quantization``). The blocks, the warping, the signals, the loss and the int8 path in
detail: docs/methods.md, "model.methods.jnds". Speed: ``scripts/bench_int8.py``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
import torch.ao.nn.quantized as nnq
import torch.nn.functional as F
from torch import nn
from torch.ao.quantization import DeQuantStub, QuantStub

from model.training.losses import SequenceLoss
from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.history_rectification import RectifiableHistory
from model.methods.quantization import (
    conv_relu,
    convert_to_int8,
    is_calibrated,
    is_int8,
    prepare_qat,
    set_observers,
)
from model.methods.registry import MethodSpec, register
from model.ops.demodulate import demodulation_divisor
from model.ops.kernels import apply_pixel_kernels
from model.ops.pyramid import downsample2x, upsample2x
from model.ops.tonemap import log_tonemap
from model.ops.warp import backward_warp, upscale_motion

__all__ = [
    "JNDSConfig",
    "PRESETS",
    "INT8_SUFFIX",
    "JNDSNetwork",
    "JNDS",
    "compress_hdr",
    "linear_kernel_weights",
    "hierarchical_filter",
    "warp_history",
    "pack_pixels",
    "unpack_pixels",
    "INPUT_CHANNELS",
]

TAPS = 9  # 3x3 kernels everywhere, as in the paper
HDR_MAX = 65535.0  # Sec. 3.2.1: HDR inputs are clamped to [0, 65535] before compression
INPUT_GAMMA = 1.0 / 2.2  # Eq. 1
# Eq. 1's power is taken of log(1 + x) + GAMMA_OFFSET (minus the offset's power, so 0 stays 0): x ** (1/2.2)
# has an infinite slope at 0 and history inputs carry gradients, so the curve must stay differentiable there.
GAMMA_OFFSET = 1e-5

CURRENT_CHANNELS = 3 + 3 + 3 + 3 + 1 + 2  # diffuse irradiance, specular, albedo, normal, roughness, jitter
HISTORY_CHANNELS = 3 + 3 + 3 + 3 + 1  # warped diffuse, specular, albedo, normal, history-valid flag
INPUT_CHANNELS = CURRENT_CHANNELS + HISTORY_CHANNELS
GUIDE_CHANNELS = 3 + 3 + 1  # upsample block: compressed composite, compressed warped output, history-valid

# Head layouts. A filter path's native head: spatial kernel, temporal kernel, temporal blend, the last upsampling
# filter's kernel and its skip blend. A decoder level's head per path: down kernel, up kernel, skip blend; the
# bottleneck's: down kernel. The auxiliary (albedo + normal) head: spatial and temporal logits, temporal blend.
PATHS = ("diffuse", "specular")
PATH_NATIVE = 2 * TAPS + 1 + TAPS + 1
AUX_NATIVE = 2 * TAPS + 1
LEVEL_HEAD = 2 * TAPS + 1
BOTTLENECK_HEAD = TAPS
NATIVE_HEAD = len(PATHS) * PATH_NATIVE + AUX_NATIVE
UPSAMPLE_HEAD = 2 * TAPS + 1
CENTRE = TAPS // 2

INT8_SUFFIX = "-int8"


@dataclass(frozen=True)
class JNDSConfig:
    """Widths of one preset.

    input_width: the input block's channels (native resolution).
    widths: U-Net channels per level, half native resolution first; the last level is the bottleneck, and the
        filter paths get one level per entry below native resolution.
    output_width: the output block's channels (native resolution), also the features the upsample block gets.
    upsample_width: the upsample block's channels (per render pixel, each holding s x s target pixels).
    """

    input_width: int
    widths: tuple[int, ...]
    output_width: int
    upsample_width: int

    def __post_init__(self) -> None:
        if len(self.widths) < 2:
            raise ValueError(f"the U-Net needs at least two levels (an encoder and a bottleneck), got {self.widths}")
        if min(self.input_width, self.output_width, self.upsample_width, *self.widths) < 1:
            raise ValueError(f"widths must be positive: {self}")


# The paper gives no channel counts; "m" is sized like a real-time 720p network of its kind (32-64 channels at
# half resolution, three filter levels below native, ~240k parameters); "xs" (~19k) and "s" (~54k, the same
# three levels) are small enough to train on a 2-core CPU; "l" (~960k) adds a level and width.
PRESETS: dict[str, JNDSConfig] = {
    "xs": JNDSConfig(input_width=8, widths=(12, 16), output_width=8, upsample_width=12),
    "s": JNDSConfig(input_width=12, widths=(16, 20, 24), output_width=12, upsample_width=16),
    "m": JNDSConfig(input_width=16, widths=(32, 48, 64), output_width=16, upsample_width=24),
    "l": JNDSConfig(input_width=24, widths=(32, 64, 96, 128), output_width=24, upsample_width=32),
}
DEFAULT_PRESET = "s"
ALL_PRESETS = tuple(PRESETS) + tuple(f"{name}{INT8_SUFFIX}" for name in PRESETS)


def compress_hdr(x: torch.Tensor) -> torch.Tensor:
    """Eq. 1, ``log(1 + clamp(x, 0, 65535)) ** (1 / 2.2)``, with a small offset inside the power that keeps its
    slope finite at 0 (about 240; values differ from Eq. 1 by < 0.006, and 0 maps to 0)."""
    y = log_tonemap(x.clamp(0.0, HDR_MAX))
    return (y + GAMMA_OFFSET) ** INPUT_GAMMA - GAMMA_OFFSET**INPUT_GAMMA


def linear_kernel_weights(raw: torch.Tensor) -> torch.Tensor:
    """Predicted kernel taps used as linear weights, clamped to [-1, 1] (Sec. 3.2.3): no normalization, so
    kernels may sharpen (negative lobes) and need not sum to 1."""
    return raw.clamp(-1.0, 1.0)


def pack_pixels(image: torch.Tensor, scale: int, channels_last: bool = False) -> torch.Tensor:
    """(N, C, sH, sW) -> (N, C s^2, H, W): each s x s block as channels, ``pixel_unshuffle``'s layout (channel
    c * s^2 + dy * s + dx), stored channels-last if asked. One copy, where torch's pixel_unshuffle leaves the
    layout conversion to a second one."""
    if scale == 1:
        return image.contiguous(memory_format=torch.channels_last) if channels_last else image
    n, c, h, w = image.shape
    blocks = image.reshape(n, c, h // scale, scale, w // scale, scale)
    if channels_last:
        packed = blocks.permute(0, 2, 4, 1, 3, 5).reshape(n, h // scale, w // scale, c * scale * scale)
        return packed.permute(0, 3, 1, 2)
    return blocks.permute(0, 1, 3, 5, 2, 4).reshape(n, c * scale * scale, h // scale, w // scale)


def unpack_pixels(packed: torch.Tensor, scale: int) -> torch.Tensor:
    """Inverse of ``pack_pixels`` (``pixel_shuffle``'s layout), faster than torch's pixel_shuffle on the CPU."""
    if scale == 1:
        return packed
    n, c, h, w = packed.shape
    blocks = packed.reshape(n, c // (scale * scale), scale, scale, h, w)
    return blocks.permute(0, 1, 4, 2, 5, 3).reshape(n, c // (scale * scale), h * scale, w * scale)


def _float_nchw(x: torch.Tensor) -> torch.Tensor:
    # Int8 modules hand over channels-last tensors; the float heads and the per-pixel filters read their
    # outputs channel by channel, which is several times faster in the standard (NCHW) layout.
    return x.contiguous()


def _head(in_channels: int, out_channels: int) -> nn.Conv2d:
    """A float32 1x1 head (kept out of quantization). Its weights start small, so its output starts near its bias,
    which ``_init_head_biases`` sets to a sensible filter: an untrained model already passes signals through
    instead of emitting random kernels."""
    head = nn.Conv2d(in_channels, out_channels, 1)
    head.qconfig = None
    with torch.no_grad():
        head.weight.mul_(0.1)
        head.bias.zero_()
    return head


def _set_kernel_bias(bias: torch.Tensor, start: int, kind: str) -> None:
    """Bias of the TAPS channels from ``start``: "box" (1/9 each), "identity" (centre 1) or "centre" (softmax
    logits favouring the centre tap)."""
    taps = bias[start : start + TAPS]
    if kind == "box":
        taps.fill_(1.0 / TAPS)
    elif kind == "identity":
        taps.zero_()
        taps[CENTRE] = 1.0
    elif kind == "centre":
        taps.zero_()
        taps[CENTRE] = 2.0
    else:
        raise ValueError(kind)


class JNDSNetwork(nn.Module):
    """Every learned part of JNDS: input block, U-Net, output block, upsample block and their float heads.

    Written for eager-mode quantization: one QuantStub per input, a DeQuantStub before each float head, one
    FloatFunctional per concatenation, conv + ReLU pairs for fusion. Unprepared it is an ordinary float32 net.
    """

    def __init__(self, config: JNDSConfig, scale: int = 2):
        super().__init__()
        self.config = config
        self.scale = scale
        # Set once the network is int8: its quantized convolutions, concatenations and poolings work in the
        # channels-last layout, and any other layout makes them convert (or fall back to float) on every call.
        self.channels_last_inputs = False
        c0, widths = config.input_width, config.widths
        self.quant_inputs = QuantStub()
        self.input_block = nn.Sequential(conv_relu(INPUT_CHANNELS, c0, 1), conv_relu(c0, c0, 3))
        self.encoders = nn.ModuleList()
        channels = c0
        for width in widths:  # the last one is the bottleneck
            self.encoders.append(nn.Sequential(conv_relu(channels, width, 3), conv_relu(width, width, 3)))
            channels = width
        # decoders[i] produces U-Net level i (i = 0 is half native resolution) from level i + 1 and skip i.
        self.decoders = nn.ModuleList(
            nn.Sequential(conv_relu(widths[i] + widths[i + 1], widths[i], 3), conv_relu(widths[i], widths[i], 3))
            for i in range(len(widths) - 1)
        )
        self.decoder_cats = nn.ModuleList(nnq.FloatFunctional() for _ in range(len(widths) - 1))
        self.output_cat = nnq.FloatFunctional()
        self.output_block = conv_relu(c0 + widths[0], config.output_width, 3)
        self.quant_guide = QuantStub()
        self.upsample_cat = nnq.FloatFunctional()
        self.upsample_block = conv_relu(GUIDE_CHANNELS * scale**2 + config.output_width, config.upsample_width, 3)

        self.level_dequant = nn.ModuleList(DeQuantStub() for _ in widths)
        self.level_heads = nn.ModuleList(
            _head(width, len(PATHS) * (BOTTLENECK_HEAD if i == len(widths) - 1 else LEVEL_HEAD))
            for i, width in enumerate(widths)
        )
        self.output_dequant = DeQuantStub()
        self.output_head = _head(config.output_width, NATIVE_HEAD)
        self.upsample_dequant = DeQuantStub()
        self.upsample_head = _head(config.upsample_width, UPSAMPLE_HEAD * scale**2)
        self._init_head_biases()

    @torch.no_grad()
    def _init_head_biases(self) -> None:
        # Start as a plain smoothing denoiser: box kernels on the noisy signals, identity on histories and on
        # upsampled images, blend logits 0 (half history, half skip).
        last = len(self.level_heads) - 1
        for i, head in enumerate(self.level_heads):
            per_path = BOTTLENECK_HEAD if i == last else LEVEL_HEAD
            for p in range(len(PATHS)):
                _set_kernel_bias(head.bias, p * per_path, "box")
                if i != last:
                    _set_kernel_bias(head.bias, p * per_path + TAPS, "identity")
        bias = self.output_head.bias
        for p in range(len(PATHS)):
            start = p * PATH_NATIVE
            _set_kernel_bias(bias, start, "box")
            _set_kernel_bias(bias, start + TAPS, "identity")
            _set_kernel_bias(bias, start + 2 * TAPS + 1, "identity")
        aux = len(PATHS) * PATH_NATIVE
        _set_kernel_bias(bias, aux, "centre")
        _set_kernel_bias(bias, aux + TAPS, "centre")
        upsample = torch.zeros(UPSAMPLE_HEAD)
        _set_kernel_bias(upsample, 0, "identity")
        _set_kernel_bias(upsample, TAPS, "identity")
        # pixel_shuffle takes channel c * s^2 + sub-pixel: every target pixel starts from the same kernels.
        self.upsample_head.bias.copy_(upsample.repeat_interleave(self.scale**2))

    def forward(self, inputs: torch.Tensor) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
        """inputs (N, INPUT_CHANNELS, H, W) -> (level heads, finest first, at H/2, H/4, ...; native head
        (N, NATIVE_HEAD, H, W); output-block features, quantized in the int8 model, for ``predict_upsample``)."""
        skip = self.input_block(self.quant_inputs(self._layout(inputs)))
        x = F.avg_pool2d(skip, 2, ceil_mode=True)  # ceil: odd sizes keep their last row, like downsample2x
        levels = []
        for i, encoder in enumerate(self.encoders):
            x = encoder(F.max_pool2d(x, 2, ceil_mode=True) if i else x)
            levels.append(x)
        for i in reversed(range(len(self.decoders))):
            up = F.interpolate(x, size=levels[i].shape[-2:], mode="bilinear", align_corners=False)
            x = self.decoders[i](self.decoder_cats[i].cat([up, levels[i]], dim=1))
            levels[i] = x
        up = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
        features = self.output_block(self.output_cat.cat([skip, up], dim=1))
        level_heads = [head(_float_nchw(dequant(level))) for head, dequant, level in
                       zip(self.level_heads, self.level_dequant, levels, strict=True)]
        return level_heads, self.output_head(_float_nchw(self.output_dequant(features))), features

    def _layout(self, x: torch.Tensor) -> torch.Tensor:
        return x.contiguous(memory_format=torch.channels_last) if self.channels_last_inputs else x

    def predict_upsample(self, guide: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """guide (N, GUIDE_CHANNELS, sH, sW) and the forward's features -> upsample head (N, UPSAMPLE_HEAD, sH, sW).

        The target grid is processed packed into render pixels (``pixel_unshuffle``: each render pixel holds
        its s x s target pixels as channels) and the head unpacked again (``pixel_shuffle``): still one
        kernel per target pixel from a 3x3-render-pixel (6x6-target-pixel) neighbourhood, but the convolution
        runs at s^2 fewer positions with s^2 more channels, which int8 and float GEMMs both run far faster.
        """
        packed = pack_pixels(guide, self.scale, channels_last=self.channels_last_inputs)
        x = self.upsample_block(self.upsample_cat.cat([self.quant_guide(packed), features], dim=1))
        return unpack_pixels(self.upsample_head(_float_nchw(self.upsample_dequant(x))), self.scale)


def warp_history(history: torch.Tensor, motion: torch.Tensor, scale: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Bicubic backward warp of a pixel-centred history (N, C, sH, sW) to this frame: read at
    ``centre + s * motion`` on the s-times finer grid (motion at render resolution, (N, 2, H, W)), without the
    jitter (module docstring). Returns ``(warped, inside)`` as ``backward_warp`` does."""
    if scale != 1:
        motion = upscale_motion(motion, scale)
    return backward_warp(history, motion, mode="bicubic")


def _spatiotemporal(current: torch.Tensor, history: torch.Tensor, spatial: torch.Tensor, temporal: torch.Tensor,
                    blend_logit: torch.Tensor, history_ok: torch.Tensor, normalize: str = "none",
                    relu: bool = True) -> torch.Tensor:
    """``relu((1 - a) K_s * current + a K_t * history)``, a = sigmoid(blend) where history exists, else 0.

    normalize "none": linear kernels clamped to [-1, 1]; "softmax": kernels are logits, normalized per pixel.
    """
    if normalize == "none":
        spatial, temporal = linear_kernel_weights(spatial), linear_kernel_weights(temporal)
    blend = torch.sigmoid(blend_logit) * history_ok
    filtered = apply_pixel_kernels(current, spatial, 3, normalize=normalize)
    warped = apply_pixel_kernels(history, temporal, 3, normalize=normalize)
    blended = filtered + blend * (warped - filtered)
    return F.relu(blended) if relu else blended


def hierarchical_filter(current: torch.Tensor, history: torch.Tensor, history_ok: torch.Tensor,
                        native: torch.Tensor, levels: list[torch.Tensor]) -> torch.Tensor:
    """One filter path (Sec. 3.2.4) on linear radiance (N, C, H, W).

    native: this path's PATH_NATIVE head channels at H x W; levels: its head channels per level below native,
    finest first (LEVEL_HEAD each, BOTTLENECK_HEAD for the last).
    """
    x = _spatiotemporal(current, history, native[:, :TAPS], native[:, TAPS : 2 * TAPS],
                        native[:, 2 * TAPS : 2 * TAPS + 1], history_ok)
    skips = [x]
    for head in levels:  # down: 2x2 average pooling, then a 3x3 kernel
        x = F.relu(apply_pixel_kernels(downsample2x(x), linear_kernel_weights(head[:, :TAPS]), 3))
        skips.append(x)
    ups = [native[:, 2 * TAPS + 1 :]] + [head[:, TAPS:] for head in levels[:-1]]  # (kernel, skip blend) per level
    for level in reversed(range(len(ups))):  # up: bilinear, a 3x3 kernel, blended with the level's skip
        skip, head = skips[level], ups[level]
        up = apply_pixel_kernels(upsample2x(x, size=tuple(skip.shape[-2:])), linear_kernel_weights(head[:, :TAPS]), 3)
        blend = torch.sigmoid(head[:, TAPS : TAPS + 1])
        x = F.relu(up + blend * (skip - up))
    return x


class JNDS(RectifiableHistory, Method):
    """Joint denoiser and supersampler; ``preset`` "xs" / "s" / "m" / "l", or with "-int8" for the QAT model.

    State (render resolution unless noted): ``diffuse`` filtered demodulated diffuse, ``specular`` filtered
    specular, ``albedo`` / ``normal`` supersampled albedo and normal, ``output`` the last output (target
    resolution), ``history`` (N, 1, 1, 1) 1 where the state is a real previous frame (0 after a cut). In
    training mode also ``composite``, the native-resolution composite the auxiliary loss supervises.
    """

    name = "jnds"
    learned = True
    loss_weights = (0.2, 0.8)  # paper Sec. 3.3: w_spatial = 0.2, w_temporal = 1 - w_spatial, for every task
    composite_loss_weight = 1.0  # paper: every task weight is 1

    def __init__(self, preset: str = DEFAULT_PRESET, scale: int = 1):
        super().__init__(preset, scale)
        base = preset.removesuffix(INT8_SUFFIX)
        if base not in PRESETS:
            raise KeyError(f"jnds has no preset {preset!r}; presets: {', '.join(ALL_PRESETS)}")
        self.preset_config = PRESETS[base]
        self.quantized = preset.endswith(INT8_SUFFIX)
        self.network = JNDSNetwork(self.preset_config, scale)
        if self.quantized:
            prepare_qat(self.network)
        self._init_rectification()

    # ------------------------------------------------------------------------------------- modes

    @property
    def is_int8(self) -> bool:
        """True once ``for_inference`` converted the network to int8 modules."""
        return is_int8(self.network)

    def train(self, mode: bool = True) -> JNDS:
        super().train(mode)
        if self.quantized and not self.is_int8:
            # Activation ranges follow the data while training and stay fixed in evaluation, so an evaluated
            # QAT model computes exactly what its int8 conversion will.
            set_observers(self.network, mode)
        return self

    def for_inference(self) -> JNDS:
        """Eval mode; an int8 preset on the CPU is converted to real int8 modules (in place, not trainable after).

        An int8 preset stays the fake-quantized model on other devices (no int8 kernels there) and, with a
        warning, when it has never seen data (untrained: its activation ranges are unset). Float32 presets stay
        in the standard layout: channels_last convolutions make the whole step slower (the filters read the
        heads' outputs channel by channel), see ``scripts/bench_int8.py``.
        """
        self.eval()
        if not self.quantized or self.is_int8 or any(p.device.type != "cpu" for p in self.parameters()):
            return self
        if not is_calibrated(self.network):
            warnings.warn(f"{self.label} has not seen any data, so it has no activation ranges to convert to int8; "
                          "running the fake-quantized model", stacklevel=2)
            return self
        convert_to_int8(self.network)
        self.network.channels_last_inputs = True
        return self

    def float_twin(self) -> JNDS | None:
        """The float32 network of the same architecture, for counting parameters and FLOPs of an int8 model:
        its packed int8 weights are not torch parameters, and torch's FLOP counter skips quantized kernels."""
        return JNDS(self.preset.removesuffix(INT8_SUFFIX), self.scale) if self.is_int8 else None

    def parameter_count(self) -> int:
        twin = self.float_twin()
        return twin.parameter_count() if twin is not None else super().parameter_count()

    def load_float_weights(self, state_dict: dict[str, torch.Tensor]) -> None:
        """Load a float32 JNDS state dict of the same base preset into this QAT model (the paper's second phase).

        Parameter names agree (``conv_relu``), so only the quantizers' buffers are absent from it; they are
        left as they are and set by the first training steps.
        """
        if not self.quantized or self.is_int8:
            raise ValueError("load_float_weights is for an int8 preset before conversion")
        missing, unexpected = self.load_state_dict(state_dict, strict=False)
        if unexpected:
            raise KeyError(f"not parameters of {self.label}: {', '.join(unexpected)}")
        not_quantizer = [name for name in missing if "fake_quant" not in name and "activation_post_process" not in name]
        if not_quantizer:
            raise KeyError(f"float32 state dict lacks parameters of {self.label}: {', '.join(not_quantizer)}")

    def load_initial_weights(self, state_dict: dict[str, torch.Tensor]) -> None:
        if self.quantized and not any("fake_quant" in name or "activation_post_process" in name
                                      for name in state_dict):
            self.load_float_weights(state_dict)
        else:
            super().load_initial_weights(state_dict)

    # -------------------------------------------------------------------------------------- step

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        state = drop_history(state, frame)
        if state is None:
            state = self._empty_state(frame)
        diffuse, specular = self._lobes(frame)
        irradiance = diffuse / demodulation_divisor(frame.albedo)

        # Previous filtered signals, bicubic-warped to this frame's pixel centres (no jitter: module docstring).
        previous = torch.cat([state["diffuse"], state["specular"], state["albedo"], state["normal"]], dim=1)
        warped, inside = warp_history(previous, frame.motion)
        history_ok = state["history"] * inside.to(previous.dtype)
        # Bicubic overshoots at edges: radiance stays >= 0 and albedo in [0, 1].
        history = {"diffuse": warped[:, 0:3].clamp_min(0.0), "specular": warped[:, 3:6].clamp_min(0.0),
                   "albedo": warped[:, 6:9].clamp(0.0, 1.0), "normal": warped[:, 9:12]}
        # rectify_history: both filtered lobes clipped to this frame's, before the network and the filters read them
        history["diffuse"] = self.rectified(history["diffuse"], irradiance)
        history["specular"] = self.rectified(history["specular"], specular)

        inputs = self._network_inputs(frame, irradiance, specular, history, history_ok)
        level_heads, native_head, features = self.network(inputs)

        filtered = {}
        current = {"diffuse": irradiance, "specular": specular}
        for p, path in enumerate(PATHS):
            native = native_head[:, p * PATH_NATIVE : (p + 1) * PATH_NATIVE]
            levels = []
            for i, head in enumerate(level_heads):
                per_path = head.shape[1] // len(PATHS)
                levels.append(head[:, p * per_path : (p + 1) * per_path])
            filtered[path] = hierarchical_filter(current[path], history[path], history_ok, native, levels)

        # Albedo and normal share one normalized spatiotemporal filter (Sec. 3.2.4). Its output skips the ReLU
        # the paper puts after every filter: a convex combination keeps albedo in [0, 1] anyway, and a ReLU
        # would clip the normals' negative components.
        aux = native_head[:, len(PATHS) * PATH_NATIVE :]
        guides = _spatiotemporal(torch.cat([frame.albedo, frame.normal], dim=1),
                                 torch.cat([history["albedo"], history["normal"]], dim=1),
                                 aux[:, :TAPS], aux[:, TAPS : 2 * TAPS], aux[:, 2 * TAPS :], history_ok,
                                 normalize="softmax", relu=False)
        albedo, normal = guides[:, :3], guides[:, 3:]
        composite = filtered["diffuse"] * demodulation_divisor(albedo) + filtered["specular"]

        output = self._upsample(composite, features, state["output"], frame, state["history"])
        new_state = {"diffuse": filtered["diffuse"], "specular": filtered["specular"], "albedo": albedo,
                     "normal": normal, "output": output, "history": torch.ones_like(state["history"])}
        if self.training:
            new_state["composite"] = composite
        return output, new_state

    # ----------------------------------------------------------------------------------- helpers

    @staticmethod
    def _lobes(frame: FrameBatch) -> tuple[torch.Tensor, torch.Tensor]:
        if frame.diffuse is None or frame.specular is None:
            return frame.color, torch.zeros_like(frame.color)  # no lobe split: all of it is "diffuse"
        return frame.diffuse, frame.specular

    def _empty_state(self, frame: FrameBatch) -> State:
        n, _, h, w = frame.color.shape
        like = frame.color
        zeros = like.new_zeros((n, 3, h, w))
        return {"diffuse": zeros, "specular": zeros, "albedo": zeros, "normal": zeros,
                "output": like.new_zeros((n, 3, h * self.scale, w * self.scale)),
                "history": like.new_zeros((n, 1, 1, 1))}

    def _network_inputs(self, frame: FrameBatch, irradiance: torch.Tensor, specular: torch.Tensor,
                        history: dict[str, torch.Tensor], history_ok: torch.Tensor) -> torch.Tensor:
        n, _, h, w = frame.color.shape
        roughness = frame.roughness if frame.roughness is not None else frame.color.new_ones((n, 1, h, w))
        jitter = frame.jitter.to(frame.color.dtype).view(n, 2, 1, 1).expand(n, 2, h, w)
        inputs = torch.cat([
            compress_hdr(irradiance), compress_hdr(specular), frame.albedo, frame.normal, roughness, jitter,
            compress_hdr(history["diffuse"]) * history_ok, compress_hdr(history["specular"]) * history_ok,
            history["albedo"] * history_ok, history["normal"] * history_ok, history_ok.expand(n, 1, h, w),
        ], dim=1)
        return inputs

    def _upsample(self, composite: torch.Tensor, features: torch.Tensor, previous_output: torch.Tensor,
                  frame: FrameBatch, has_history: torch.Tensor) -> torch.Tensor:
        """Upsample block: bilinear 2x (at scale 1 the composite as is), then a predicted 3x3 kernel blended
        with the bicubic-warped previous output by a predicted per-pixel weight."""
        upsampled = upsample2x(composite) if self.scale == 2 else composite
        warped, inside = warp_history(previous_output, frame.motion, self.scale)
        warped = warped.clamp_min(0.0)
        history_ok = has_history * inside.to(warped.dtype)
        n, _, h, w = upsampled.shape
        guide = torch.cat([compress_hdr(upsampled), compress_hdr(warped) * history_ok,
                           history_ok.expand(n, 1, h, w)], dim=1)
        head = self.network.predict_upsample(guide, features)
        return _spatiotemporal(upsampled, warped, head[:, :TAPS], head[:, TAPS : 2 * TAPS], head[:, 2 * TAPS :],
                               history_ok)

    # -------------------------------------------------------------------------------------- loss

    def auxiliary_loss(self, frames: list[FrameBatch], states: list[State]) -> torch.Tensor | None:
        """The composite task: 0.2 SMAPE + 0.8 temporal L1 of the native composite against the reference
        box-filtered to native resolution (the scale-1 reference), times ``composite_loss_weight``."""
        if any(frame.reference is None for frame in frames) or any("composite" not in s for s in states):
            return None
        targets = [F.avg_pool2d(frame.reference, self.scale) if self.scale > 1 else frame.reference
                   for frame in frames]
        loss = SequenceLoss(*self.loss_weights)([s["composite"] for s in states], targets)
        return self.composite_loss_weight * loss.total


register(
    MethodSpec(
        name="jnds",
        description="joint denoising + supersampling (JNDS): half-resolution U-Net, hierarchical diffuse / "
        "specular kernel filters, kernel-predicted upsampling, bicubic history; '-int8': QAT, int8 on the CPU",
        factory=lambda preset, scale: JNDS(preset, scale),
        presets=ALL_PRESETS,
        default_preset=DEFAULT_PRESET,
        scales=(1, 2),
        optional_buffers=("diffuse", "specular", "roughness"),  # the lobe split of the colour, roughness as a guide
        learned=True,
    )
)
