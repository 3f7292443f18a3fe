"""Non-learned baselines: the noisy input (the floor), temporal accumulation alone, and an SVGF-style filter.

All three filter at render resolution; at scale 2 their output is upscaled with bicubic interpolation
(`RenderResolutionFilter`), which gives the "X + bicubic" baselines the joint denoise-and-upscale methods are
compared against. None has parameters, so `parameter_count()` is 0.

Temporal methods keep their history in the current frame's pixel grid and, each frame, backward-warp it with the
frame's motion and jitter (`model.ops.warp`), test it against the previous depth and normal
(`model.ops.reproject`) and blend with a per-pixel sample count (`model.ops.accumulate`).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.registry import MethodSpec, register
from model.ops.accumulate import accumulate, accumulate_moments
from model.ops.reproject import reproject_history
from model.ops.rectify import rectify_accumulated
from model.ops.tonemap import luminance
from model.ops.demodulate import demodulate

__all__ = [
    "bicubic_upscale",
    "RenderResolutionFilter",
    "Identity",
    "TemporalAccumulation",
    "SVGFParams",
    "SVGF",
]

def bicubic_upscale(image: torch.Tensor, scale: int) -> torch.Tensor:
    """Upscale (N, C, H, W) by an integer `scale` with bicubic interpolation (align_corners=False), clamped >= 0.

    The clamp is there because the bicubic kernel overshoots at edges and radiance must stay non-negative.
    `scale == 1` returns the image unchanged.
    """
    if scale == 1:
        return image
    upscaled = F.interpolate(image, scale_factor=scale, mode="bicubic", align_corners=False)
    return upscaled.clamp_min(0.0)


class RenderResolutionFilter(Method):
    """A method that filters at render resolution; at scale 2 the filtered frame is bicubic-upscaled."""

    denoises_at_render_resolution = True

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        output, state = self.filter_frame(frame, state)
        return bicubic_upscale(output, self.scale), state

    @abc.abstractmethod
    def filter_frame(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        """Filter one frame at render resolution: (N, 3, H, W) radiance and the new state."""


def reproject_state(
    frame: FrameBatch,
    state: State,
    names: tuple[str, ...],
    depth_rel_tol: float,
    normal_cos_tol: float,
) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """Warp the history buffers `names` of `state` into this frame (`model.ops.reproject.reproject_history`,
    one call for all of them); returns (warped by name, count, valid)."""
    stacked = torch.cat([state[name] for name in names], dim=1)
    warped, count, valid = reproject_history(stacked, state["count"], frame.depth, frame.normal, state["depth"],
                                             state["normal"], frame.motion, frame.jitter, state["jitter"],
                                             depth_rel_tol=depth_rel_tol, normal_cos_tol=normal_cos_tol)
    sizes = [state[name].shape[1] for name in names]
    return dict(zip(names, torch.split(warped, sizes, dim=1))), count, valid


class Identity(RenderResolutionFilter):
    """The noisy input itself: the floor every method must beat."""

    name = "identity"

    def filter_frame(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        return frame.color, {}


class TemporalAccumulation(RenderResolutionFilter):
    """Reprojected exponential accumulation of the albedo-demodulated illumination, with no spatial filter.

    Presets pick `alpha_min`, the weight of the newest frame once the running mean has become an exponential
    average: "default" 0.1 (about 10 frames of memory: less noise, more lag), "fast" 0.2 (about 5 frames:
    reacts sooner to moving light and shading changes, noisier).

    State: "history" (accumulated illumination, N x 3 x H x W), "count" (per-pixel sample count, N x 1), and
    the frame's "depth" and "normal" for the next frame's disocclusion test.
    """

    name = "accumulation"
    ALPHA_MIN = {"default": 0.1, "fast": 0.2, "rectified": 0.1}
    # "rectified": the warped history is variance-clipped against this frame's illumination
    # (model.ops.rectify.rectify_accumulated).

    def __init__(self, preset: str = "default", scale: int = 1,
                 depth_rel_tol: float = 0.1, normal_cos_tol: float = 0.9):
        super().__init__(preset, scale)
        if preset not in self.ALPHA_MIN:
            raise KeyError(f"{self.name} has no preset {preset!r}; presets: {', '.join(self.ALPHA_MIN)}")
        self.alpha_min = self.ALPHA_MIN[preset]
        self.depth_rel_tol = depth_rel_tol
        self.normal_cos_tol = normal_cos_tol

    def filter_frame(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        # Accumulate illumination (color / albedo), not color: warping resamples the history bilinearly, which
        # blurs it a little every frame. Texture lives in the albedo, which is noise-free and taken fresh from
        # this frame, so after remodulation texture detail stays sharp and only the smooth illumination is blurred.
        illumination, divisor = demodulate(frame.color, frame.albedo)
        state = drop_history(state, frame)
        if state is None:
            accumulated, count = accumulate(illumination, None, None, None, alpha_min=self.alpha_min)
        else:
            warped, history_count, valid = reproject_state(frame, state, ("history",),
                                                             self.depth_rel_tol, self.normal_cos_tol)
            history = warped["history"]
            if self.preset == "rectified":
                history = rectify_accumulated(history, illumination)
            accumulated, count = accumulate(illumination, history, history_count, valid,
                                            alpha_min=self.alpha_min)
        new_state = {"history": accumulated, "count": count, "depth": frame.depth, "normal": frame.normal,
                     "jitter": frame.jitter}
        return accumulated * divisor, new_state


@dataclass(frozen=True)
class SVGFParams:
    """Parameters of the SVGF-style filter (Schied et al. 2017, "Spatiotemporal Variance-Guided Filtering").

    Defaults are the paper's unless noted.
    """

    alpha_color: float = 0.2  # newest frame's minimum weight in the illumination history
    alpha_moments: float = 0.2  # the same for the luminance moments
    min_temporal_count: int = 4  # below this many history samples, variance is estimated spatially
    variance_radius: int = 3  # spatial variance estimate window: (2r + 1)^2 = 7 x 7
    atrous_levels: int = 5  # a-trous iterations, the i-th with tap spacing 2^i (reach 2 * 2^4 = 32 px)
    sigma_depth: float = 1.0  # depth edge-stopping: tolerance in units of the local depth gradient
    sigma_normal: float = 128.0  # normal edge-stopping: exponent on max(0, n_p . n_q)
    sigma_luminance: float = 4.0  # luminance edge-stopping: tolerance in units of the local noise std. dev.
    # Not in the paper: a depth tolerance of this fraction of the depth, so a fronto-parallel surface (zero depth
    # gradient) with tiny depth noise from the renderer is not torn apart by 0 / 0 comparisons.
    depth_rel_eps: float = 1e-2
    # Reprojection test (model.ops.reproject), the same as TemporalAccumulation's.
    depth_rel_tol: float = 0.1
    normal_cos_tol: float = 0.9


# B3-spline taps, separable: the 5 x 5 a-trous kernel is the outer product h h^T.
B3_SPLINE = (1.0 / 16.0, 1.0 / 4.0, 3.0 / 8.0, 1.0 / 4.0, 1.0 / 16.0)
GAUSSIAN_3X3 = (0.25, 0.5, 0.25)
LUMINANCE_EPS = 1e-10  # keeps the luminance test finite where the variance is 0 (no noise: any difference stops)
DEPTH_EPS = 1e-6  # keeps the depth test finite where there is no surface (depth 0)
MIN_COSINE = 1e-20  # normals at 90 degrees or more: log stays finite, the weight is cut to 0
LOG_WEIGHT_CUTOFF = -40.0  # exp(-40) = 4e-18: smaller edge-stopping weights are 0 (and their squares normal floats)


def depth_gradient(depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel depth gradient (d depth / dx, d depth / dy), each (N, 1, H, W), in depth units per pixel.

    Of the forward and backward differences the one smaller in magnitude is taken: on a plane both equal its
    slope, while on the last pixel before a depth edge the difference across the edge is the larger one, so the
    gradient stays that of the pixel's own surface and the depth test still stops the filter at the edge.
    """
    padded = F.pad(depth, (1, 1, 1, 1), mode="replicate")
    forward_x = padded[..., 1:-1, 2:] - depth
    backward_x = depth - padded[..., 1:-1, :-2]
    forward_y = padded[..., 2:, 1:-1] - depth
    backward_y = depth - padded[..., :-2, 1:-1]
    gradient_x = torch.where(forward_x.abs() < backward_x.abs(), forward_x, backward_x)
    gradient_y = torch.where(forward_y.abs() < backward_y.abs(), forward_y, backward_y)
    return gradient_x, gradient_y


def gaussian_blur3x3(image: torch.Tensor) -> torch.Tensor:
    """3 x 3 binomial blur of (N, 1, H, W), replicating the border (SVGF's pre-filter of the variance)."""
    taps = torch.tensor(GAUSSIAN_3X3, dtype=image.dtype, device=image.device)
    kernel = (taps[:, None] * taps[None, :]).view(1, 1, 3, 3)
    return F.conv2d(F.pad(image, (1, 1, 1, 1), mode="replicate"), kernel)


class Guide:
    """Per-frame buffers the edge-stopping functions compare, zero-padded once for every tap of one filter pass.

    `tap(dy, dx)` returns the neighbour at offset (dy, dx) pixels of each guide buffer plus an "inside" flag
    that is 0 for neighbours outside the image (zero padding), so such taps get no weight.
    """

    def __init__(self, frame: FrameBatch, radius: int, params: SVGFParams, extra: torch.Tensor | None = None):
        self.height, self.width = frame.height, frame.width
        self.radius = radius
        self.params = params
        self.depth = frame.depth
        self.normal = frame.normal
        self.gradient_x, self.gradient_y = depth_gradient(frame.depth)
        self.depth_tolerance_floor = params.depth_rel_eps * frame.depth + DEPTH_EPS
        inside = torch.ones_like(frame.depth)
        parts = [frame.depth, frame.normal, inside] + ([extra] if extra is not None else [])
        self.padded = F.pad(torch.cat(parts, dim=1), (radius, radius, radius, radius))

    def tap(self, dy: int, dx: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(depth, normal, inside, extra channels) of the neighbour at (dy, dx), each in this frame's grid."""
        r = self.radius
        shifted = self.padded[..., r + dy: r + dy + self.height, r + dx: r + dx + self.width]
        return shifted[:, 0:1], shifted[:, 1:4], shifted[:, 4:5], shifted[:, 5:]

    def geometry_log_weight(self, depth_q: torch.Tensor, normal_q: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
        """log of w_depth * w_normal for the neighbour at (dy, dx):

        w_depth = exp(-|z_p - z_q| / (sigma_z |grad z(p) . (p - q)| + eps z_p)), w_normal = max(0, n_p . n_q)^sigma_n.

        Returned as a logarithm so each tap needs one exp for all its edge-stopping terms (a float power costs
        as much as an exp, and dominated the filter's run time). The cosine is floored at MIN_COSINE rather than
        0: log(0) takes a slow path on CPU, and the floor's weight rounds to 0 in `edge_stopping_weight` anyway.
        """
        expected_change = (self.gradient_x * dx + self.gradient_y * dy).abs()
        tolerance = self.params.sigma_depth * expected_change + self.depth_tolerance_floor
        depth_term = (self.depth - depth_q).abs() / tolerance
        cosine = (self.normal * normal_q).sum(dim=1, keepdim=True).clamp(MIN_COSINE, 1.0)
        return self.params.sigma_normal * torch.log(cosine) - depth_term


def edge_stopping_weight(log_weight: torch.Tensor) -> torch.Tensor:
    """exp(log_weight), with weights below exp(LOG_WEIGHT_CUTOFF) set to exactly 0.

    They are negligible next to the centre tap's (at least 0.14), and exp of a very negative number gives
    float32 denormals, which CPUs compute with several times slower (exp itself, then every product).
    """
    return torch.exp(log_weight.clamp_min(LOG_WEIGHT_CUTOFF)) * (log_weight > LOG_WEIGHT_CUTOFF)


def spatial_variance(frame: FrameBatch, mean: torch.Tensor, mean_sq: torch.Tensor, count: torch.Tensor,
                     params: SVGFParams) -> torch.Tensor:
    """SVGF's variance estimate for young history: luminance moments averaged over a 7 x 7 window.

    Neighbours count with the depth and normal edge-stopping weights only, so the window does not mix surfaces
    and the estimate measures noise rather than geometry edges. As in the authors' implementation the result is
    boosted by 4 / count: with 1 to 3 samples the history is noisier than the estimate suggests, and a larger
    variance makes the a-trous filter blur more while there is little history.
    """
    radius = params.variance_radius
    guide = Guide(frame, radius, params, extra=torch.cat([mean, mean_sq], dim=1))
    weight_sum = torch.ones_like(mean)
    moments = torch.cat([mean, mean_sq], dim=1)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy == 0 and dx == 0:
                continue
            depth_q, normal_q, inside_q, moments_q = guide.tap(dy, dx)
            weight = edge_stopping_weight(guide.geometry_log_weight(depth_q, normal_q, dy, dx)) * inside_q
            weight_sum = weight_sum + weight
            moments = moments + weight * moments_q
    moments = moments / weight_sum
    variance = (moments[:, 1:2] - moments[:, 0:1].square()).clamp_min(0.0)
    return variance * (params.min_temporal_count / count.clamp_min(1.0))


def atrous_level(frame: FrameBatch, illumination: torch.Tensor, variance: torch.Tensor, spacing: int,
                 params: SVGFParams) -> tuple[torch.Tensor, torch.Tensor]:
    """One a-trous iteration: the 5 x 5 B3-spline kernel with taps `spacing` pixels apart, edge-stopped.

    Weight of neighbour q for pixel p: h(i) h(j) * w_depth * w_normal * w_luminance, with
    w_luminance = exp(-|l_p - l_q| / (sigma_l sqrt(gauss3x3(var)(p)) + eps)) on the illumination's luminance.
    The centre tap always has weight h(0)^2 (a pixel without a surface has a zero normal and would otherwise
    reject itself). The variance is filtered alongside with the squared weights, which is the variance of the
    weighted mean of independent samples; the next iteration uses it as its noise estimate.
    """
    radius = 2 * spacing
    lum = luminance(illumination)
    lum_tolerance = params.sigma_luminance * gaussian_blur3x3(variance).clamp_min(0.0).sqrt() + LUMINANCE_EPS
    guide = Guide(frame, radius, params, extra=torch.cat([illumination, variance, lum], dim=1))
    centre = B3_SPLINE[2] * B3_SPLINE[2]
    weight_sum = torch.full_like(lum, centre)
    filtered = centre * illumination
    filtered_variance = centre * centre * variance
    for i, h_y in enumerate(B3_SPLINE):
        for j, h_x in enumerate(B3_SPLINE):
            if i == 2 and j == 2:
                continue
            dy, dx = (i - 2) * spacing, (j - 2) * spacing
            depth_q, normal_q, inside_q, extra_q = guide.tap(dy, dx)
            illumination_q, variance_q, lum_q = extra_q[:, 0:3], extra_q[:, 3:4], extra_q[:, 4:5]
            luminance_term = (lum - lum_q).abs() / lum_tolerance
            log_weight = guide.geometry_log_weight(depth_q, normal_q, dy, dx) - luminance_term
            weight = edge_stopping_weight(log_weight) * (inside_q * (h_y * h_x))
            weight_sum = weight_sum + weight
            filtered = filtered + weight * illumination_q
            filtered_variance = filtered_variance + weight.square() * variance_q
    return filtered / weight_sum, filtered_variance / weight_sum.square()


class SVGF(RenderResolutionFilter):
    """SVGF-style filter: temporal accumulation, a variance estimate, then an edge-stopped a-trous wavelet filter.

    Per frame, on the albedo-demodulated illumination (see `TemporalAccumulation` for why demodulate):
    1. reproject and accumulate the illumination and its luminance moments (mean, mean of squares);
    2. variance = temporal (moments) where the history has at least `min_temporal_count` samples, else the
       spatial 7 x 7 estimate (`spatial_variance`);
    3. `atrous_levels` a-trous iterations with spacing 1, 2, 4, 8, 16 (`atrous_level`); the first iteration's
       output is the history fed back to the next frame, as in SVGF: it is less noisy than the raw accumulation,
       yet only lightly blurred, so it does not smear detail over time;
    4. remodulate by the albedo.

    State: "history" (N x 3), "mean", "mean_sq" (luminance moments), "count", "depth", "normal".
    """

    name = "svgf"

    PRESETS = ("default", "rectified")  # rectified: the illumination history clipped as accumulation's preset

    def __init__(self, preset: str = "default", scale: int = 1, params: SVGFParams | None = None):
        super().__init__(preset, scale)
        if preset not in self.PRESETS:
            raise KeyError(f"{self.name} has no preset {preset!r}; presets: {', '.join(self.PRESETS)}")
        self.params = params or SVGFParams()

    def filter_frame(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        params = self.params
        illumination, divisor = demodulate(frame.color, frame.albedo)
        state = drop_history(state, frame)
        if state is None:
            accumulated, count = accumulate(illumination, None, None, None, alpha_min=params.alpha_color)
            mean, mean_sq, temporal_variance = accumulate_moments(illumination, None, None, None, None,
                                                                  alpha_min=params.alpha_moments)
        else:
            warped, history_count, valid = reproject_state(frame, state, ("history", "mean", "mean_sq"),
                                                             params.depth_rel_tol, params.normal_cos_tol)
            history = warped["history"]
            if self.preset == "rectified":
                history = rectify_accumulated(history, illumination)
            accumulated, count = accumulate(illumination, history, history_count, valid,
                                            alpha_min=params.alpha_color)
            mean, mean_sq, temporal_variance = accumulate_moments(
                illumination, warped["mean"], warped["mean_sq"], history_count, valid,
                alpha_min=params.alpha_moments)

        young = count < params.min_temporal_count
        if bool(young.any()):
            variance = torch.where(young, spatial_variance(frame, mean, mean_sq, count, params), temporal_variance)
        else:
            variance = temporal_variance

        filtered = accumulated
        feedback = accumulated
        for level in range(params.atrous_levels):
            filtered, variance = atrous_level(frame, filtered, variance, 2 ** level, params)
            if level == 0:
                feedback = filtered
        new_state = {"history": feedback, "mean": mean, "mean_sq": mean_sq, "count": count,
                     "depth": frame.depth, "normal": frame.normal, "jitter": frame.jitter}
        return filtered * divisor, new_state


register(MethodSpec(
    name=Identity.name,
    description="noisy input, the floor",
    factory=lambda preset, scale: Identity(preset, scale),
    scales=(1, 2),
    optional_buffers=(),
))
register(MethodSpec(
    name=TemporalAccumulation.name,
    description="temporal accumulation alone (reprojected, depth/normal tested, albedo demodulated)",
    factory=lambda preset, scale: TemporalAccumulation(preset, scale),
    presets=tuple(TemporalAccumulation.ALPHA_MIN),
    scales=(1, 2),
    optional_buffers=(),
))
register(MethodSpec(
    name=SVGF.name,
    description="SVGF-style filter (Schied et al. 2017): accumulation, variance, 5-level edge-stopped a-trous",
    factory=lambda preset, scale: SVGF(preset, scale),
    presets=SVGF.PRESETS,
    scales=(1, 2),
    optional_buffers=(),
))
