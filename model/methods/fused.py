"""The fused family: OIDN per frame for the spatial estimate, a small recurrent network for temporal reuse.

OIDN on one 1 spp frame is the strongest spatial denoiser our users have, but it lacks time: its output flickers,
and TAA on top of it lags behind moving light. This family keeps OIDN for the spatial part and learns the temporal
part (after AFN's fusion of a per-frame and an accumulated branch): per frame a small U-Net reads OIDN's estimate
``s``, the noisy frame, the guides, the reprojected history ``h``, its rectified form ``r`` and the clipped running
mean ``c`` of OIDN's estimates, and predicts softmax fusion weights over (``s``, ``h``, ``r``, ``c``) and a 3 x 3
output kernel. Where there is no history the output is OIDN's estimate alone, so it cannot ghost there; the fusion
head starts at TAA's weights, so training starts from OIDN + TAA.

The run-time settings recorded with the weights (the recurrence, the kernel limit, the running mean's window, the
stale-history tests, the sample mean, the albedo detail, the unjittered estimate) are the properties of ``Fused``.
Presets pick OIDN's quality (``fast``, ``balanced``, ``high``); the network is the same for all three. The steps of
a frame and why each setting exists: docs/methods.md, "model.methods.fused".
"""

from __future__ import annotations

import dataclasses
import functools

import torch
import torch.nn.functional as F
from torch import nn

from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.oidn import QUALITIES, oidn_albedo, oidn_denoise
from model.methods.oidn_taa import reinhard, reinhard_inverse
from model.methods.registry import MethodSpec, register
from model.ops import native
from model.ops.box_filter import replicated_box_extremes
from model.ops.graph_breaks import outside_compiled_graph
from model.ops.jittered_albedo import gather_samples, sample_weights, texture_detail
from model.ops.kernels import apply_pixel_kernels
from model.ops.native.features import fused_features_x1
from model.ops.native.rectify import clip_pair_x1
from model.ops.native.resample import sample_mean_resample_x1, unjittered_resample_x1
from model.ops.native.tail import fused_tail_x1
from model.ops.native.unet_joints import joints_usable, mean_pool2, upsample_cat
from model.ops.native.warps import reproject_x1
from model.ops.pyramid import block_mean
from model.ops.rectify import clip_to_bounds, moment_bounds, neighbourhood_moments
from model.ops.reproject import disocclusion_mask
from model.ops.sample_mean import sample_mean_spread, update_sample_mean
from model.ops.separable_sample import scaled_bicubic, scaled_nearest
from model.ops.stale_history import stale_history_trust
from model.ops.warp import backward_warp, upscale_motion

__all__ = ["Fused", "FusionNet", "frame_of_sample_mean", "frame_samples", "head_candidates", "sample_mean_resample",
           "unjittered_resample"]

CANDIDATES = 4  # spatial estimate, history, rectified history, clipped running mean
LEGACY_CANDIDATES = 3  # checkpoints from before the running mean: spatial estimate, history, rectified history
MEAN_FRAMES = 16.0  # the running mean's 1 / n weights stop falling here by default (then an exponential average;
# training samples hold 12 frames, so the count input stays near what training saw); also the count input's scale
MEAN_WINDOW_KEY = "mean_window_frames"  # state-dict entry: where this model's running mean stops (absent: MEAN_FRAMES)
MEAN_INPUTS = 3 + 3 + 1  # the running mean, |mean - s| and log(1 + frames in it), at render resolution
NEW_CANDIDATE_WEIGHT = 0.01  # the clipped mean's share when fine-tuning starts from a legacy checkpoint
KERNEL = 3
HIDDEN = 4  # recurrent feature channels carried from frame to frame
MAX_HISTORY = 8.0  # the history-length input saturates here (longer histories look alike to the network)
# Initial fusion: TAA's 0.2 * current + 0.8 * rectified history, almost nothing on the raw history or the means.
INITIAL_WEIGHTS = (0.2, 0.002, 0.796, 0.002)
LEGACY_INITIAL_WEIGHTS = (0.2, 0.002, 0.798)
INITIAL_CENTRE_LOGIT = 7.0  # the 3 x 3 kernel starts as (almost) the identity: 0.993 on the centre tap
WIDTH = 16
RECURRENCE_KEY = "recurrence_before_kernel"  # state-dict entry: 1 = the blend before the kernel is the history
KERNEL_LIMIT_KEY = "kernel_limit_pixels"  # state-dict entry: frames with more render pixels skip the kernel (0: none do)
STALE_TEST_KEY = "stale_history_sigmas"  # state-dict entry: the stale-history test's threshold (0 or absent: no test)
STALE_REGION_KEY = "stale_region_window"  # state-dict entry: the regional stale-history test's window (0 or absent:
# none)
STALE_TEST_BLOCK = 9  # the test's window: 81 samples of the 1 spp frame, a standard error of a ninth of their spread
SAMPLE_MEAN_KEY = "sample_mean_window"  # state-dict entry: OIDN reads a running mean of this many 1 spp frames
# (0 or absent: the single frame)
SAMPLE_MEAN_STALE_SIGMAS = 2.0  # the sample mean restarts where the new samples are this many standard errors off it
SAMPLE_MEAN_TRUST_KEY = "sample_mean_share_power"  # state-dict entry: the sample mean keeps the network's history
# share to this power of its frames (absent: SAMPLE_MEAN_TRUST_POWER)
SAMPLE_MEAN_TRUST_POWER = 2.0
UNJITTER_KEY = "estimate_unjittered"  # state-dict entry: 1 = at 1x, OIDN's estimate is read at the pixel centres from
# its samples' jittered positions (absent: 0 at 1x; at 2x the estimate is always resampled so)
ALBEDO_DETAIL_KEY = "albedo_detail_window"  # state-dict entry: at 2x, the output takes the texture detail of the
# albedo gathered on the target grid over up to this many jittered frames (0 or absent: none)

# The settings a model runs that are no weights, each with a ``set_`` method and a state-dict entry (above): name ->
# (whether it needs the network's running mean, what a model without it lacks; shipping refuses it there).
RUN_TIME_SETTINGS: dict[str, tuple[bool, str]] = {
    "history_before_kernel": (False, "no choice of recurrence"),
    "kernel_max_pixels": (False, "no output kernel to limit"),
    "mean_max_frames": (True, "no running mean to set a window for"),
    "stale_test_sigmas": (True, "no running mean for the stale-history test"),
    "stale_region_pixels": (True, "no running mean for the stale-history test"),
    "sample_mean_frames": (False, "no spatial denoiser to feed a sample mean"),
    "sample_mean_trust_power": (False, "no spatial denoiser to feed a sample mean"),
    "albedo_detail_frames": (False, "no albedo to gather on a target grid"),
    "unjitter_estimate": (False, "no spatial estimate to resample"),
}

# The run-time settings the shipped models of a scale run (``pretrained/fused-*``; a test holds them to the shipped
# weights), which a model trained from nothing starts with (``use_shipped_settings``). Each was measured on shipped
# weights and kept where it helped held-out recipes (docs/results/findings.md).
# ``fused-high-x1`` alone keeps its sample mean at power 3: it never trained with the mean, and a model that did needs
# no higher power; a model trained from nothing trains with it.
SHIPPED_SETTINGS: dict[int, dict[str, bool | int | float]] = {
    1: {"history_before_kernel": True, "kernel_max_pixels": 32768, "mean_max_frames": 8, "stale_test_sigmas": 0.5,
        "stale_region_pixels": 33, "sample_mean_frames": 8, "sample_mean_trust_power": 2.0, "unjitter_estimate": True},
    2: {"history_before_kernel": False, "kernel_max_pixels": 0, "mean_max_frames": 8, "stale_test_sigmas": 1.0,
        "stale_region_pixels": 33, "sample_mean_frames": 8, "sample_mean_trust_power": 2.0,
        "albedo_detail_frames": 8, "unjitter_estimate": True},
}


def frame_samples(frame: FrameBatch) -> torch.Tensor:
    """The 1 spp colour with the guides OIDN reads of the same samples (its albedo, the normals), (N, 9, H, W)."""
    return torch.cat([frame.color, oidn_albedo(frame), frame.normal], dim=1)


def frame_of_sample_mean(frame: FrameBatch, samples: torch.Tensor) -> FrameBatch:
    """The frame OIDN denoises from a running mean of ``frame_samples``: the mean colour with the mean guides. OIDN
    asks for guides averaged over the same samples as the colour; over jittered frames a texture finer than a pixel
    averages to its mean in the colour, and one frame's albedo would still show it at a single sample's position."""
    return dataclasses.replace(frame, color=samples[:, :3], albedo=samples[:, 3:6], normal=samples[:, 6:9],
                               specular_albedo=None)


def unjittered_resample(image: torch.Tensor, jitter: torch.Tensor, scale: int) -> torch.Tensor:
    """Resample a render-resolution image whose pixel (x, y) holds the sample at (x + 0.5 + jitter) onto the
    target grid: target pixel centre P (in render pixels, P = (X + 0.5) / scale) reads the image at P - jitter.
    Bicubic, border padding, clamped to the min/max of the source pixels around each sample (bicubic overshoots
    next to a bright emitter, and in x / (1 + x) space an overshoot past 1 would map back to unbounded radiance)."""
    return _read_within_bounds(image, _source_bounds(image), jitter, scale)


def _source_bounds(image: torch.Tensor) -> torch.Tensor:
    """Each pixel's 3x3 neighbourhood max and min (N, 2C, H, W), edges replicated: the 2x2 source pixels a bilinear
    read would use lie inside it."""
    return torch.cat(replicated_box_extremes(image, 3), dim=1)


def _read_within_bounds(image: torch.Tensor, bounds: torch.Tensor, jitter: torch.Tensor, scale: int) -> torch.Tensor:
    # Target pixel centre P = (X + 0.5) / scale render pixels reads the source at P - jitter, i.e. at pixel
    # (X + 0.5) / scale - 0.5 - jitter: a shifted, scaled grid, read in separable phases (model.ops.separable_sample).
    channels = image.shape[1]
    shift = -jitter.to(image.dtype)
    resampled = scaled_bicubic(image, shift, scale)
    bounds = scaled_nearest(bounds, shift, scale)
    return torch.clamp(resampled, min=bounds[:, channels:], max=bounds[:, :channels])


def sample_mean_resample(image: torch.Tensor, jitter: torch.Tensor, count: torch.Tensor, scale: int) -> torch.Tensor:
    """``unjittered_resample`` for an estimate made from a sample mean of ``count`` (N, 1, H, W) frames: this frame's
    samples weigh 1 / count and sit at its jitter, the older frames' jitters average to the pixel centre. So each
    target pixel blends the image read at this jitter and at none in those proportions (1 frame: the plain resample)."""
    current = _upsample_values(1.0 / count.clamp_min(1.0), scale)
    bounds = _source_bounds(image)
    # at 1x a read at no shift is the image itself (the cubic's taps at whole pixels are 1, 0, 0, 0)
    centred = image if scale == 1 else _read_within_bounds(image, bounds, torch.zeros_like(jitter), scale)
    return centred + current * (_read_within_bounds(image, bounds, jitter, scale) - centred)


def head_candidates(head_rows: int, scale: int) -> int:
    """How many fusion candidates a network's head of ``head_rows`` outputs predicts weights for at ``scale``
    (the head: scale^2 sub-pixels x (candidates + 3 x 3 kernel taps), then the hidden features)."""
    return (head_rows - HIDDEN) // scale ** 2 - KERNEL * KERNEL


def _conv(inputs: int, outputs: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(inputs, outputs, 3, padding=1), nn.ReLU(inplace=True))


class FusionNet(nn.Module):
    """Two-level U-Net at render resolution; the head predicts scale^2 sub-pixels' weights and kernels each."""

    def __init__(self, inputs: int, scale: int, width: int = WIDTH, candidates: int = CANDIDATES):
        super().__init__()
        self.scale = scale
        self.candidates = candidates
        self.width = width
        self.encoder = nn.Sequential(_conv(inputs, width), _conv(width, width))
        self.bottom = nn.Sequential(_conv(width, 2 * width), _conv(2 * width, 2 * width))
        self.decoder = _conv(3 * width, width)
        per_pixel = candidates + KERNEL * KERNEL
        self.head = nn.Conv2d(width, scale * scale * per_pixel + HIDDEN, 1)
        self._initialise_head(per_pixel)

    def _initialise_head(self, per_pixel: int) -> None:
        nn.init.zeros_(self.head.weight[: self.scale ** 2 * per_pixel])
        bias = torch.zeros(per_pixel)
        weights = torch.tensor(INITIAL_WEIGHTS if self.candidates == CANDIDATES else LEGACY_INITIAL_WEIGHTS)
        bias[:self.candidates] = torch.log(weights)
        bias[self.candidates + KERNEL * KERNEL // 2] = INITIAL_CENTRE_LOGIT
        with torch.no_grad():
            self.head.bias.zero_()
            # Channel layout (PixelShuffle): channel c * scale^2 + sub-pixel, so each value repeats per sub-pixel.
            self.head.bias[: self.scale ** 2 * per_pixel] = bias.repeat_interleave(self.scale ** 2)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(fusion logits (N, 3, sH, sW), kernel logits (N, 9, sH, sW), hidden features (N, HIDDEN, H, W))."""
        top = self.encoder(features)
        h, w = top.shape[-2:]
        if joints_usable(top):  # bf16 channels_last inference: the joints as native passes, the same values
            bottom = self.bottom(mean_pool2(top))
            joined = upsample_cat(top, bottom) if joints_usable(bottom) else None
        else:
            bottom, joined = self.bottom(F.avg_pool2d(top, 2, ceil_mode=True)), None
        if joined is None:
            up = F.interpolate(bottom, size=(h, w), mode="bilinear", align_corners=False)
            joined = torch.cat([top, up], dim=1)
        out = self.head(self.decoder(joined))
        per_pixel = self.scale ** 2 * (self.candidates + KERNEL * KERNEL)
        fine = F.pixel_shuffle(out[:, :per_pixel], self.scale) if self.scale > 1 else out[:, :per_pixel]
        # contiguous first: in channels_last the hidden rows are a strided slice, and tanh over it is much slower
        # (the same values)
        return fine[:, :self.candidates], fine[:, self.candidates:], torch.tanh(out[:, per_pixel:].contiguous())


class Fused(Method):
    """OIDN + learned temporal reuse (see the module docstring)."""

    name = "fused"
    learned = True
    # Frame-to-frame change matters as much as per-frame error here: the point of the method is stability.
    loss_weights = (1.0, 0.5)

    def __init__(self, preset: str = "balanced", scale: int = 1, depth_rel_tol: float = 0.1,
                 normal_cos_tol: float = 0.9, history_before_kernel: bool = False, kernel_max_pixels: int = 0):
        super().__init__(preset, scale)
        if preset not in QUALITIES:
            raise KeyError(f"{self.name} has no preset {preset!r}; presets: {', '.join(QUALITIES)}")
        self.spatial_prior = preset
        self.depth_rel_tol = depth_rel_tol
        self.normal_cos_tol = normal_cos_tol
        self.net = self._network(CANDIDATES)
        # A buffer, so checkpoints record which recurrence their weights run; mirrored in a Python bool so a step
        # never reads a device tensor to branch on it.
        self.register_buffer(RECURRENCE_KEY, torch.tensor(float(history_before_kernel)))
        self._history_before_kernel = bool(history_before_kernel)
        self.register_buffer(KERNEL_LIMIT_KEY, torch.tensor(0.0))
        self.set_kernel_max_pixels(kernel_max_pixels)
        self.register_buffer(MEAN_WINDOW_KEY, torch.tensor(MEAN_FRAMES))
        self.set_mean_max_frames(int(MEAN_FRAMES))
        self.register_buffer(STALE_TEST_KEY, torch.tensor(0.0))
        self._stale_test_sigmas = 0.0
        self.register_buffer(STALE_REGION_KEY, torch.tensor(0.0))
        self._stale_region_pixels = 0
        self.register_buffer(SAMPLE_MEAN_KEY, torch.tensor(0.0))
        self._sample_mean_frames = 0
        self.register_buffer(SAMPLE_MEAN_TRUST_KEY, torch.tensor(SAMPLE_MEAN_TRUST_POWER))
        self._sample_mean_trust_power = SAMPLE_MEAN_TRUST_POWER
        self.register_buffer(ALBEDO_DETAIL_KEY, torch.tensor(0.0))
        self._albedo_detail_frames = 0
        self.register_buffer(UNJITTER_KEY, torch.tensor(float(scale > 1)))
        self._unjitter_estimate = scale > 1

    @property
    def history_before_kernel(self) -> bool:
        """Whether the next frame's history is the fused blend before the kernel (else the filtered output)."""
        return self._history_before_kernel

    def set_history_before_kernel(self, value: bool) -> None:
        getattr(self, RECURRENCE_KEY).fill_(float(value))
        self._history_before_kernel = bool(value)

    @property
    def kernel_max_pixels(self) -> int:
        """Frames with more render pixels than this output the fused blend unfiltered (0: every frame is filtered).
        The kernel is learned at 128x128, where much texture is finer than a pixel and its averaging is what the
        reference holds; on frames twice as wide the same textures are resolved and the averaging erases them."""
        return self._kernel_max_pixels

    def set_kernel_max_pixels(self, value: int) -> None:
        refusal = "kernel_max_pixels must be a whole number of pixels >= 0 (0: no limit)"
        self._kernel_max_pixels = self._store_count(KERNEL_LIMIT_KEY, value, 0, refusal)

    @property
    def mean_max_frames(self) -> int:
        """The running mean's window: 1 / n weights up to this many frames, then an exponential average of that
        length. Training samples hold 12 frames, so training never tells a window of 8 from one of 16; a long stream
        does: the mean is resampled with the history every frame, and over a slow camera's 64 frames a 16-frame
        window blurred a checker floor's edges frame by frame."""
        return self._mean_max_frames

    def set_mean_max_frames(self, value: int) -> None:
        self._mean_max_frames = self._store_count(MEAN_WINDOW_KEY, value, 1,
                                                  "mean_max_frames must be a whole number of frames >= 1")

    @property
    def stale_test_sigmas(self) -> float:
        """Where the running mean's window mean differs from the 1 spp frame's by more than this many standard
        errors (``model.ops.stale_history``), the weights of the history and of the clipped mean fall off and go to
        OIDN's estimate (0: no test). The network weighs its candidates per pixel and lags behind a moving light
        over whole regions; the test sees such a change in the unbiased samples, which the network's inputs
        cannot tell from OIDN's blotches."""
        return self._stale_test_sigmas

    def set_stale_test_sigmas(self, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0 or value == float("inf"):
            raise ValueError(f"stale_test_sigmas must be a finite number of standard errors >= 0 (0: no test), "
                             f"got {value!r}")
        getattr(self, STALE_TEST_KEY).fill_(float(value))
        self._stale_test_sigmas = float(value)

    @property
    def stale_region_pixels(self) -> int:
        """The regional stale-history test's window, odd, in render pixels (0: none; ``model.ops.stale_history``):
        where the root mean square of the test's z's over it is past ``REGION_SIGMAS``, the history's weights fall
        off too (``stale_test_sigmas`` > 0) and the sample mean restarts (``sample_mean_frames`` > 0). A light that
        moves a little every frame is seen by few single windows and by most regions."""
        return self._stale_region_pixels

    def set_stale_region_pixels(self, value: int) -> None:
        refusal = "stale_region_pixels must be an odd whole number of pixels, or 0 (no regional test)"
        if isinstance(value, int) and value > 0 and value % 2 == 0:  # _store_count refuses the rest
            raise ValueError(f"{refusal}, got {value!r}")
        self._stale_region_pixels = self._store_count(STALE_REGION_KEY, value, 0, refusal)

    @property
    def sample_mean_frames(self) -> int:
        """OIDN denoises a reprojected running mean of up to this many 1 spp frames instead of the single frame
        (0: the single frame; ``model.ops.sample_mean``). The mean keeps the frames' samples only where the network
        trusted its history in the frame before, and restarts where the stale-history test or the geometry test
        fails, so OIDN reads more samples where the scene holds still and one where it changed. At 2x the estimate
        is resampled where its samples lie on average (``sample_mean_resample``)."""
        return self._sample_mean_frames

    def set_sample_mean_frames(self, value: int) -> None:
        self._sample_mean_frames = self._store_count(SAMPLE_MEAN_KEY, value, 0,
                                                     "sample_mean_frames must be a whole number of frames >= 0 "
                                                     "(0: OIDN reads the single frame)")

    @property
    def sample_mean_trust_power(self) -> float:
        """The sample mean keeps its frames in the proportion the network trusted its history in the frame before,
        raised to this power (``_history_share``): a higher one restarts it sooner where the network begins to doubt
        its history, as around a moving light. A model not trained with its sample mean leans on the mean where it
        lags, and a higher power keeps it nearer the fresh samples."""
        return self._sample_mean_trust_power

    def set_sample_mean_trust_power(self, value: float) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < float("inf"):
            raise ValueError(f"sample_mean_trust_power must be a finite number > 0, got {value!r}")
        getattr(self, SAMPLE_MEAN_TRUST_KEY).fill_(float(value))
        self._sample_mean_trust_power = float(value)

    @property
    def albedo_detail_frames(self) -> int:
        """At 2x, the output is multiplied by the texture detail of the albedo gathered on the target grid from up to
        this many jittered frames (0: none; ``model.ops.jittered_albedo``). OIDN and the network work at the render
        resolution, so texture finer than a render pixel (a brick wall's mortar, a checker floor) comes out at its
        pixel average; the guides are noise-free, and each frame's jittered samples say what lies in one sub-pixel.
        Only the output takes the detail: the history stays as the network made it, so the detail never compounds."""
        return self._albedo_detail_frames

    def set_albedo_detail_frames(self, value: int) -> None:
        refusal = "albedo_detail_frames must be a whole number of frames >= 0 (0: no texture detail)"
        if self.scale == 1 and isinstance(value, int) and not isinstance(value, bool) and value > 0:
            raise ValueError(f"albedo_detail_frames needs a target grid finer than the render (scale 2); this model "
                             f"is at scale 1, got {value!r}")
        self._albedo_detail_frames = self._store_count(ALBEDO_DETAIL_KEY, value, 0, refusal)

    @property
    def unjitter_estimate(self) -> bool:
        """Whether OIDN's estimate is read at the pixel centres from where its samples lie, this frame's sub-pixel
        jitter off them (``unjittered_resample``; from a sample mean, ``sample_mean_resample``). At 2x it always is:
        the target grid needs a resample anyway. At 1x a renderer's TAA jitter puts every sample up to half a pixel
        off the pixel it is stored in, so the estimate is the image shifted by the jitter, while the history and the
        reference are centred, and reading it back at the centres helps even OIDN alone. Frames without jitter read
        it unchanged."""
        return self._unjitter_estimate

    def set_unjitter_estimate(self, value: bool) -> None:
        if not isinstance(value, bool):
            raise ValueError(f"unjitter_estimate must be true or false, got {value!r}")
        if self.scale > 1 and not value:
            raise ValueError("unjitter_estimate cannot be false at 2x: the target grid reads OIDN's estimate at its "
                             "samples' positions by construction")
        getattr(self, UNJITTER_KEY).fill_(float(value))
        self._unjitter_estimate = value

    def use_shipped_settings(self) -> None:
        for setting, value in SHIPPED_SETTINGS[self.scale].items():
            getattr(self, f"set_{setting}")(value)

    def run_time_settings(self) -> dict[str, bool | int | float]:
        return {setting: getattr(self, setting) for setting in RUN_TIME_SETTINGS}

    def _store_count(self, key: str, value: int, minimum: int, refusal: str) -> int:
        """A whole-number setting checked and written to its state-dict buffer, so checkpoints record it."""
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ValueError(f"{refusal}, got {value!r}")
        getattr(self, key).fill_(float(value))
        return value

    def _network(self, candidates: int, width: int = WIDTH) -> FusionNet:
        inputs = 3 * 7 + 3 + HIDDEN + (2 if self.scale > 1 else 0)  # 7 images, depth, valid, length, hidden (jitter)
        if candidates == CANDIDATES:
            inputs += MEAN_INPUTS
        return FusionNet(inputs, self.scale, width=width, candidates=candidates)

    @property
    def has_mean(self) -> bool:
        return self.net.candidates == CANDIDATES

    def _candidates_in(self, state_dict: dict[str, torch.Tensor]) -> int:
        return head_candidates(state_dict["net.head.weight"].shape[0], self.scale)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """Load a checkpoint of either network: one from before the running mean rebuilds this method as the
        three-candidate network it was trained as (the same outputs and cost as then)."""
        if RECURRENCE_KEY not in state_dict:  # saved before the choice existed: the output was the history
            state_dict = {**state_dict, RECURRENCE_KEY: torch.tensor(0.0)}
        if KERNEL_LIMIT_KEY not in state_dict:  # saved before the limit existed: every frame filtered
            state_dict = {**state_dict, KERNEL_LIMIT_KEY: torch.tensor(0.0)}
        if MEAN_WINDOW_KEY not in state_dict:  # saved before the window was a setting: the default one
            state_dict = {**state_dict, MEAN_WINDOW_KEY: torch.tensor(MEAN_FRAMES)}
        if STALE_TEST_KEY not in state_dict:  # saved before the test existed: none
            state_dict = {**state_dict, STALE_TEST_KEY: torch.tensor(0.0)}
        if STALE_REGION_KEY not in state_dict:  # saved before the regional test existed: none
            state_dict = {**state_dict, STALE_REGION_KEY: torch.tensor(0.0)}
        if SAMPLE_MEAN_KEY not in state_dict:  # saved before the sample mean existed: OIDN reads the single frame
            state_dict = {**state_dict, SAMPLE_MEAN_KEY: torch.tensor(0.0)}
        if SAMPLE_MEAN_TRUST_KEY not in state_dict:  # saved before the power was a setting: the one they ran
            state_dict = {**state_dict, SAMPLE_MEAN_TRUST_KEY: torch.tensor(SAMPLE_MEAN_TRUST_POWER)}
        if ALBEDO_DETAIL_KEY not in state_dict:  # saved before the texture detail existed: none
            state_dict = {**state_dict, ALBEDO_DETAIL_KEY: torch.tensor(0.0)}
        if UNJITTER_KEY not in state_dict:  # saved before the setting existed: as the step ran then
            state_dict = {**state_dict, UNJITTER_KEY: torch.tensor(float(self.scale > 1))}
        candidates = self._candidates_in(state_dict)
        if candidates not in (CANDIDATES, LEGACY_CANDIDATES):
            raise ValueError(f"fused: a checkpoint with {candidates} fusion candidates is not a fused network "
                             f"({LEGACY_CANDIDATES} or {CANDIDATES})")
        width = state_dict["net.head.weight"].shape[1]  # a widened network (fused_growth) loads at its own width
        if candidates != self.net.candidates or width != self.net.width:
            device = self.net.head.weight.device
            self.net = self._network(candidates, width).to(device)
        result = super().load_state_dict(state_dict, strict=strict, assign=assign)
        self._history_before_kernel = bool(getattr(self, RECURRENCE_KEY).item() > 0.5)
        self.set_kernel_max_pixels(int(round(getattr(self, KERNEL_LIMIT_KEY).item())))
        self.set_mean_max_frames(int(round(getattr(self, MEAN_WINDOW_KEY).item())))
        self.set_stale_test_sigmas(float(getattr(self, STALE_TEST_KEY).item()))
        self.set_stale_region_pixels(int(round(getattr(self, STALE_REGION_KEY).item())))
        self.set_sample_mean_frames(int(round(getattr(self, SAMPLE_MEAN_KEY).item())))
        self.set_sample_mean_trust_power(float(getattr(self, SAMPLE_MEAN_TRUST_KEY).item()))
        self.set_albedo_detail_frames(int(round(getattr(self, ALBEDO_DETAIL_KEY).item())))
        self.set_unjitter_estimate(bool(getattr(self, UNJITTER_KEY).item() > 0.5))
        return result

    def load_initial_weights(self, state_dict: dict[str, torch.Tensor]) -> None:
        """``--init-from``: a three-candidate checkpoint starts this network as the same function, nearly: the
        new inputs' weights are zero and the clipped running mean starts at ``NEW_CANDIDATE_WEIGHT``. The weights
        come with their recurrence: a fine-tune trains the recurrence the model it starts from runs."""
        if self._candidates_in(state_dict) != LEGACY_CANDIDATES or not self.has_mean:
            self.load_state_dict(state_dict)
            return
        expanded = dict(state_dict)
        first = "net.encoder.0.0.weight"
        old = state_dict[first]
        grown = old.new_zeros(old.shape[0], old.shape[1] + MEAN_INPUTS, *old.shape[2:])
        grown[:, :old.shape[1]] = old  # the new inputs come after every old one
        expanded[first] = grown
        sub = self.scale ** 2
        old_weight, old_bias = state_dict["net.head.weight"], state_dict["net.head.bias"]
        weight = old_weight.new_zeros(self.net.head.weight.shape)
        bias = old_bias.new_zeros(self.net.head.bias.shape)
        # Head rows are channel * scale^2 + sub-pixel (PixelShuffle); the new candidate goes after the old three.
        for channel in range(LEGACY_CANDIDATES + KERNEL * KERNEL):
            new = channel if channel < LEGACY_CANDIDATES else channel + CANDIDATES - LEGACY_CANDIDATES
            weight[new * sub:(new + 1) * sub] = old_weight[channel * sub:(channel + 1) * sub]
            bias[new * sub:(new + 1) * sub] = old_bias[channel * sub:(channel + 1) * sub]
        # Its logit: the old candidates' log-sum-exp (their biases) plus log of its share.
        old_logits = old_bias[:LEGACY_CANDIDATES * sub].view(LEGACY_CANDIDATES, sub)
        start = torch.logsumexp(old_logits, dim=0) + torch.log(torch.tensor(NEW_CANDIDATE_WEIGHT))
        for new in range(LEGACY_CANDIDATES, CANDIDATES):
            bias[new * sub:(new + 1) * sub] = start
        rows = (LEGACY_CANDIDATES + KERNEL * KERNEL) * sub
        weight[CANDIDATES * sub + KERNEL * KERNEL * sub:] = old_weight[rows:]  # the hidden features' rows
        bias[CANDIDATES * sub + KERNEL * KERNEL * sub:] = old_bias[rows:]
        expanded["net.head.weight"], expanded["net.head.bias"] = weight, bias
        self.load_state_dict(expanded)

    def for_inference(self) -> Fused:
        """Eval mode with the network in channels_last: faster convolutions on the CPU, the same arithmetic (tests
        compare it with the training form)."""
        self.eval()
        self.net.to(memory_format=torch.channels_last)
        return self

    def spatial_estimate(self, frame: FrameBatch) -> torch.Tensor:
        estimate = frame.spatial_estimate
        if estimate is None:
            estimate = _spatial_denoise(frame, self.preset)
        return reinhard(estimate.to(frame.color.dtype))

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        state = drop_history(state, frame)
        n, _, height, width = frame.color.shape
        motion_out = upscale_motion(frame.motion, self.scale) if self.scale > 1 else frame.motion
        samples = samples_count = previous_samples = None
        if self._sample_mean_frames:
            samples = frame_samples(frame)
            previous_samples = None if state is None else state.get("samples")
            if previous_samples is not None and previous_samples.shape != samples.shape:
                previous_samples = None  # a session from before the sample mean averaged the guides
        reprojected = None if state is None else self._reproject(frame, state, motion_out, previous_samples)
        if samples is not None:
            samples, samples_count = self._sample_mean(frame, state, samples, reprojected)
            s = reinhard(_spatial_denoise(frame_of_sample_mean(frame, samples), self.preset).to(frame.color.dtype))
        else:
            s = self.spatial_estimate(frame)
        # The network reads ``s`` as OIDN made it (at 1x its weights were trained so); the candidates, their clip
        # and the running mean take the estimate read at the pixel centres.
        native_x1 = self._native_x1(n, "resample", s)
        if not self._unjitter_estimate:
            s_out = s
        elif samples_count is not None:
            s_out = sample_mean_resample_x1(s, frame.jitter, samples_count) if native_x1 else \
                sample_mean_resample(s, frame.jitter, samples_count, self.scale)
        else:
            s_out = unjittered_resample_x1(s, frame.jitter) if native_x1 else \
                unjittered_resample(s, frame.jitter, self.scale)
        if self.has_mean and self._native_x1(n, "features", s, s_out, frame.color):
            inputs = self._network_inputs_native(frame, state, s, s_out, reprojected)
        else:
            inputs = self._network_inputs(frame, state, s, s_out, reprojected)
        features, candidates, valid, valid_out, length, mean, count, mean_r = inputs
        logits, kernels, new_hidden = self.net(features)
        unfiltered = bool(self._kernel_max_pixels) and height * width > self._kernel_max_pixels
        linear = None  # the output in linear radiance, where the native pass made it
        if unfiltered and self.has_mean and self._native_x1(n, "tail", logits):
            trust = None
            if self._stale_test_sigmas > 0 and state is not None:
                trust = stale_history_trust(frame.color, reinhard_inverse(mean_r), self._stale_test_sigmas,
                                            self._stale_region_pixels, STALE_TEST_BLOCK)
            blended, linear, kept = fused_tail_x1(logits, candidates, trust, valid, samples_count,
                                                  self._sample_mean_trust_power)
            samples_count = kept  # None without a sample mean
            output = blended
        else:
            # contiguous: from a channels_last network each candidate's weight is a strided slice otherwise
            weights = torch.softmax(logits, dim=1).contiguous()
            if samples is not None:
                share = self._history_share(weights, self._sample_mean_trust_power).detach()
                samples_count = samples_count * block_mean(share, self.scale)
            if self._stale_test_sigmas > 0 and state is not None and self.has_mean:
                weights = self._distrust_stale(weights, frame.color, reinhard_inverse(mean_r), valid)
            # from the first product, not from sum()'s 0: one full-frame pass fewer, the same values
            blended = weights[:, :1] * candidates[0]
            for k, candidate in enumerate(candidates[1:], start=1):
                blended = blended + weights[:, k:k + 1] * candidate
            output = blended if unfiltered else apply_pixel_kernels(blended, kernels, KERNEL, normalize="softmax")
        history = blended if self.history_before_kernel else output
        new_state = {"history": history, "hidden": new_hidden, "length": length, "depth": frame.depth,
                     "normal": frame.normal, "jitter": frame.jitter}
        if self.has_mean:
            new_state.update(mean=mean, count=count)
        if samples is not None:
            new_state.update(samples=samples, samples_count=samples_count)
        output = reinhard_inverse(output) if linear is None else linear
        if self._albedo_detail_frames and self.scale > 1:
            detail, gathered = self._texture_detail(frame, state, motion_out, valid_out)
            output = output * detail
            new_state.update(gathered)
        return output, new_state

    def _native_x1(self, n: int, source: str, *tensors: torch.Tensor) -> bool:
        """Whether this step's 1x work may run ``source``'s native kernels: scale 1, one image, ``native.usable``."""
        return self.scale == 1 and n == 1 and native.usable(source, *tensors)

    def _network_inputs(self, frame: FrameBatch, state: State | None, s: torch.Tensor, s_out: torch.Tensor,
                        reprojected: tuple[torch.Tensor | None, ...] | None) -> tuple:
        """(the network's input, the fusion candidates, valid, valid at the output, the new history length, the
        running mean and its count, the mean at render resolution) for OIDN's estimate ``s`` and its resample
        ``s_out``."""
        n, _, height, width = frame.color.shape
        mean = count = None  # the running mean and its frame count, when the network has one
        valid_out = None
        if state is None:
            valid = torch.zeros_like(frame.depth, dtype=torch.bool)
            history, hidden = s_out, frame.color.new_zeros(n, HIDDEN, height, width)
            length = torch.zeros_like(frame.depth)
        else:
            history, hidden, length, valid, mean, count = reprojected[:6]
            valid_out = _upsample_mask(valid, self.scale)
            history = torch.where(valid_out, history, s_out)
            hidden = hidden * valid
        if self.has_mean:
            if mean is None:
                mean, count = s_out, torch.ones_like(frame.depth)
            else:  # 1 / n weights over the frames the history held, the current one included
                count_out = _upsample_values(count, self.scale)
                mean = mean + (s_out - mean) / count_out
        # both clipped candidates are clipped to s's neighbourhood
        if n == 1 and native.usable("rectify", s_out, history):
            rectified, clipped_mean = clip_pair_x1(s_out, history, mean if self.has_mean else None)
        else:
            box = moment_bounds(*neighbourhood_moments(s_out))
            rectified = clip_to_bounds(history, *box)
            clipped_mean = clip_to_bounds(mean, *box) if self.has_mean else None
        length = torch.where(valid, (length + 1).clamp_max(MAX_HISTORY), torch.zeros_like(length))

        def at_render(image: torch.Tensor) -> torch.Tensor:
            return block_mean(image, self.scale)

        history_r, rectified_r = at_render(history), at_render(rectified)
        depth = frame.depth / frame.depth.flatten(1).amax(dim=1).clamp_min(1e-6).view(-1, 1, 1, 1)
        parts = [s, reinhard(frame.color), frame.albedo, frame.normal, history_r, rectified_r,
                 (history_r - s).abs(), depth, valid.to(s.dtype), length / MAX_HISTORY, hidden]
        if self.scale > 1:
            parts.append(frame.jitter.view(n, 2, 1, 1).expand(n, 2, height, width).to(s.dtype))
        candidates = [s_out, history, rectified]
        if self.has_mean:
            mean_r = at_render(mean)
            parts += [mean_r, (mean_r - s).abs(), torch.log1p(count) / torch.log1p(torch.tensor(MEAN_FRAMES))]
            candidates.append(clipped_mean)
        features = _features(parts, self.net.head.weight.is_contiguous(memory_format=torch.channels_last))
        return features, candidates, valid, valid_out, length, mean, count, (mean_r if self.has_mean else None)

    def _network_inputs_native(self, frame: FrameBatch, state: State | None, s: torch.Tensor, s_out: torch.Tensor,
                               reprojected: tuple[torch.Tensor | None, ...] | None) -> tuple:
        """``_network_inputs`` at 1x for one image with a running mean, as one native pass
        (``model.ops.native.features``): the same values to float rounding."""
        history = valid = length = hidden = mean = count = None
        if state is not None:
            history, hidden, length, valid, mean, count = reprojected[:6]
        depth_max = frame.depth.flatten(1).amax(dim=1).clamp_min(1e-6)
        count_norm = torch.log1p(torch.tensor(MEAN_FRAMES))
        history, rectified, mean, clipped_mean, length, features = fused_features_x1(
            s, s_out, frame.color, frame.albedo, frame.normal, history, valid, length, hidden, mean, count,
            frame.depth, depth_max, MAX_HISTORY, count_norm, self.network_input_dtype())
        if valid is None:
            valid = torch.zeros_like(frame.depth, dtype=torch.bool)
        if count is None:
            count = torch.ones_like(frame.depth)
        return features, [s_out, history, rectified, clipped_mean], valid, valid, length, mean, count, mean

    def _texture_detail(self, frame: FrameBatch, state: State | None, motion_out: torch.Tensor,
                        valid_out: torch.Tensor | None) -> tuple[torch.Tensor, State]:
        """The output's factor of texture detail (``model.ops.jittered_albedo``) and the gathered albedo's state:
        the albedo OIDN reads (diffuse + specular), this frame's samples added to the sums warped from the frame
        before where the geometry test holds. Bilinear: a nearest read puts samples up to half a target pixel off
        under camera motion, and gained less on the validation scenes."""
        albedo = oidn_albedo(frame).contiguous()  # frames stack channels_last, and mixed layouts are slow here
        # nearest: each sample on every sub-pixel of its render pixel, kept in the one it lies in (splat_at_jitter's
        # arithmetic), and the fallback where nothing was gathered
        upsampled = F.interpolate(albedo, scale_factor=self.scale, mode="nearest")
        new_weight = sample_weights(frame.jitter.to(albedo.dtype), self.scale, *albedo.shape[-2:])
        new_total = upsampled * new_weight
        previous = None if state is None else state.get("albedo_sum")
        if previous is None or valid_out is None or previous.shape != new_total.shape:
            total, weight = new_total, new_weight  # a new stream, or a session from before the detail
        else:
            warped, _ = backward_warp(torch.cat([previous, state["albedo_weight"]], dim=1), motion_out,
                                      mode="bilinear")
            warped = warped * valid_out
            total, weight = gather_samples(warped[:, :-1], warped[:, -1:], new_total, new_weight,
                                           self._albedo_detail_frames)
        return texture_detail(total, weight, upsampled, self.scale), {"albedo_sum": total, "albedo_weight": weight}

    def _sample_mean(self, frame: FrameBatch, state: State | None, samples: torch.Tensor,
                     reprojected: tuple[torch.Tensor | None, ...] | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The running mean of the 1 spp frames and their guides that OIDN reads (``samples``, this frame's
        ``frame_samples``), and the frames it holds (``model.ops.sample_mean``); ``reprojected``: ``_reproject``'s
        answer, the history's geometry test and the mean's samples and count warped into this frame."""
        if reprojected is None or reprojected[6] is None:
            # a new stream, or a session from before the sample mean or before it averaged the guides
            return samples, torch.ones_like(frame.depth)
        valid, warped, count = reprojected[3], reprojected[6], reprojected[7]
        return update_sample_mean(samples, warped, count, valid, self._sample_mean_frames, SAMPLE_MEAN_STALE_SIGMAS,
                                  spread=sample_mean_spread(frame.motion, frame.jitter, state["jitter"]),
                                  stale_region=self._stale_region_pixels)

    @staticmethod
    def _history_share(weights: torch.Tensor, power: float) -> torch.Tensor:
        """How much the network trusted its history against OIDN's estimate this frame, to ``power``: the history's
        and the running mean's weights over theirs plus OIDN's. The sample mean keeps its frames in that proportion,
        so where the network fell back to OIDN (changed light, a disocclusion it saw) OIDN next reads fresh samples."""
        trusted = weights[:, 1:2] + weights[:, 3:4] if weights.shape[1] > 3 else weights[:, 1:2]
        return (trusted / (trusted + weights[:, :1]).clamp_min(1e-6)) ** power

    def _distrust_stale(self, weights: torch.Tensor, noisy: torch.Tensor, mean: torch.Tensor,
                        valid: torch.Tensor) -> torch.Tensor:
        """Move the history's and the clipped mean's fusion weights to OIDN's estimate where the stale-history test
        finds the running mean (linear, render resolution) off the 1 spp frame; the rectified history keeps its
        weight, since its clip to OIDN's neighbourhood already bounds how stale it can be. Where the history is not
        valid there is nothing to distrust (the mean is OIDN's estimate itself), so a zeroed state, an engine's first
        frame, gives what no state gives."""
        trust = stale_history_trust(noisy, mean, self._stale_test_sigmas, self._stale_region_pixels, STALE_TEST_BLOCK)
        trust = _upsample_values(torch.where(valid, trust, torch.ones_like(trust)), self.scale)
        history, rectified, clipped_mean = weights[:, 1:2] * trust, weights[:, 2:3], weights[:, 3:4] * trust
        moved = weights[:, 1:2] + weights[:, 3:4] - history - clipped_mean
        return torch.cat([weights[:, :1] + moved, history, rectified, clipped_mean], dim=1)

    def _reproject(self, frame: FrameBatch, state: State, motion_out: torch.Tensor,
                   samples: torch.Tensor | None = None) -> tuple[torch.Tensor | None, ...]:
        """(history at output resolution, hidden features, history length, valid, running mean at output
        resolution, frames the mean will hold with this one, the sample mean ``samples``, its count) warped into
        this frame; the running mean's two are None when the network has no mean or the state none (a session from
        before it: the mean starts at this frame), the sample mean's when ``samples`` is None.
        Where the history is invalid the count is 1, so the caller's update replaces the mean with ``s``.
        ``motion_out``: the motion on the output grid. The buffers read with the same motion and filter are read in
        one call each: a read's arithmetic is per channel, so the values are those of separate reads."""
        with_mean = self.has_mean and "mean" in state
        if self._native_x1(frame.motion.shape[0], "reproject", frame.motion, state["history"]):
            return self._reproject_native(frame, state, samples, with_mean)
        # Bicubic: a bilinear read blurs the history a little every frame under camera motion, which adds up over
        # a long history.
        # Its overshoot is clamped: the values are x / (1 + x) in [0, 1). The running mean is read with it.
        images = torch.cat([state["history"], state["mean"]], dim=1) if with_mean else state["history"]
        images, _ = backward_warp(images, motion_out, mode="bicubic")
        images = images.clamp(0.0, 1.0 - 1e-4)
        history = images[:, :3]
        render_parts = [state["hidden"], state["length"]] + ([] if samples is None else [samples])
        render, _ = backward_warp(torch.cat(render_parts, dim=1), frame.motion, mode="bilinear")
        valid = disocclusion_mask(frame.depth, frame.normal, state["depth"], state["normal"], frame.motion,
                                  depth_rel_tol=self.depth_rel_tol, normal_cos_tol=self.normal_cos_tol,
                                  jitter=frame.jitter - state["jitter"])
        # A camera cut zeroes the state (drop_history): its normals are 0 then, which fails the test above.
        counts = ([state["count"]] if with_mean else []) + ([] if samples is None else [state["samples_count"]])
        counts = backward_warp(torch.cat(counts, dim=1), frame.motion, mode="nearest")[0] if counts else None
        mean = count = None
        if with_mean:
            window = float(self._mean_max_frames)
            count = counts[:, :1]
            mean, count = images[:, 3:], torch.where(valid, (count + 1).clamp_max(window), torch.ones_like(count))
        warped_samples = samples_count = None
        if samples is not None:
            warped_samples, samples_count = render[:, HIDDEN + 1:], counts[:, -1:]
        return (history, render[:, :HIDDEN], render[:, HIDDEN:HIDDEN + 1], valid, mean, count, warped_samples,
                samples_count)

    def _reproject_native(self, frame: FrameBatch, state: State, samples: torch.Tensor | None,
                          with_mean: bool) -> tuple[torch.Tensor | None, ...]:
        """``_reproject`` at 1x for one image as one native pass (``model.ops.native.warps``): the same reads and
        test, so the same values to float rounding."""
        cubic = [state["history"]] + ([state["mean"]] if with_mean else [])
        linear = [state["hidden"], state["length"]] + ([] if samples is None else [samples])
        nearest = ([state["count"]] if with_mean else []) + ([] if samples is None else [state["samples_count"]])
        images, render, counts, valid = reproject_x1(
            frame.motion, cubic, (0.0, 1.0 - 1e-4), linear, nearest, frame.depth, frame.normal, state["depth"],
            state["normal"], frame.jitter - state["jitter"], self.depth_rel_tol, self.normal_cos_tol)
        mean = count = None
        if with_mean:
            count = counts[:, :1]
            count = torch.where(valid, (count + 1).clamp_max(float(self._mean_max_frames)), torch.ones_like(count))
            mean = images[:, 3:]
        warped_samples = samples_count = None
        if samples is not None:
            warped_samples, samples_count = render[:, HIDDEN + 1:], counts[:, -1:]
        return (images[:, :3], render[:, :HIDDEN], render[:, HIDDEN:HIDDEN + 1], valid, mean, count, warped_samples,
                samples_count)


@outside_compiled_graph
def _spatial_denoise(frame: FrameBatch, quality: str) -> torch.Tensor:
    """OIDN's estimate (``oidn_denoise``, read from this module at each call); a native call, so a compiled step
    runs it between its graphs."""
    return oidn_denoise(frame, quality)


def _features(parts: list[torch.Tensor], channels_last: bool) -> torch.Tensor:
    """The network's input: ``parts`` concatenated along the channels, in channels_last for a network in it.
    Without gradients the parts are written straight into a channels_last tensor (cheaper than the concatenation
    and its copy); ``out=`` takes no gradient, so training concatenates."""
    if not channels_last:
        return torch.cat(parts, dim=1)
    if torch.is_grad_enabled() or torch.compiler.is_compiling():  # a compiled step fuses the two into one write
        return torch.cat(parts, dim=1).contiguous(memory_format=torch.channels_last)
    dtype = functools.reduce(torch.promote_types, [part.dtype for part in parts])
    n, _, height, width = parts[0].shape
    out = torch.empty((n, sum(part.shape[1] for part in parts), height, width), dtype=dtype, device=parts[0].device,
                      memory_format=torch.channels_last)
    return torch.cat(parts, dim=1, out=out)


def _upsample_values(values: torch.Tensor, scale: int) -> torch.Tensor:
    if scale == 1:
        return values
    return F.interpolate(values, scale_factor=scale, mode="nearest")


def _upsample_mask(mask: torch.Tensor, scale: int) -> torch.Tensor:
    if scale == 1:
        return mask
    return _upsample_values(mask.to(torch.float32), scale) > 0.5


register(MethodSpec(
    name=Fused.name,
    description="OIDN per frame + a learned recurrent fusion with its reprojected, rectified history "
                "(per-pixel fusion weights and 3x3 kernels; temporal upsampling at 2x)",
    factory=lambda preset, scale: Fused(preset, scale),
    presets=QUALITIES,
    default_preset="balanced",
    scales=(1, 2),
    optional_buffers=("specular_albedo",),  # OIDN's albedo guide adds the specular albedo
    learned=True,
))
