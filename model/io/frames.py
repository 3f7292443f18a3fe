"""The frame bundle: the one data format every part of the project speaks, and its conventions.

A frame bundle is one path-traced frame at render resolution (1 sample per pixel) with its auxiliary buffers,
plus, for training and evaluation data, converged references at one or more target resolutions. Arrays are NumPy,
height x width x channels (HWC), float32; one-component buffers are (H, W). The conventions, exactly (data from
other renderers is converted to them):

- image coordinates are continuous, origin at the top-left corner of pixel (0, 0), x right, y down;
- the frame's one sample in pixel (x, y) lies at (x + 0.5 + jitter_x, y + 0.5 + jitter_y), jitter in [-0.5, 0.5];
- ``motion`` = (position in frame t-1's unjittered image of the surface this frame's sample hit) minus (this frame's
  sample position), in render pixels, so ``prev = p + motion``;
- references are box-filtered pixel averages at the target resolution (the scale-1 one the 2x2 mean of the scale-2
  one when both exist, ``box_downsample``); ``depth`` is the distance along the ray, ``normal`` world space.

Every buffer's meaning and range: docs/frame-format.md. ``BUFFERS`` describes every buffer once (EXR channel names,
required or not, value range); the EXR reader and writer and the validator all work from it.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass, field
from typing import Literal

import numpy as np


@dataclass(frozen=True)
class BufferSpec:
    """What one buffer holds and how it is stored.

    ``low`` / ``high`` bound every component (None: unbounded); values may stray outside by ``tolerance``
    because renderers and half-float storage round. Radiance has tolerance 0: any negative is a bug.
    """

    name: str
    components: tuple[str, ...]  # EXR channel suffixes, in array channel order
    required: bool
    resolution: Literal["render", "target"]
    low: float | None
    high: float | None
    tolerance: float
    meaning: str

    @property
    def channels(self) -> tuple[str, ...]:
        """EXR channel names, e.g. ("color.R", "color.G", "color.B")."""
        return tuple(f"{self.name}.{component}" for component in self.components)

    @property
    def is_scalar(self) -> bool:
        """One-component buffers are stored as (H, W) arrays, not (H, W, 1)."""
        return len(self.components) == 1


def _spec(
    name: str,
    components: str,
    required: bool,
    low: float | None,
    high: float | None,
    tolerance: float,
    meaning: str,
    resolution: Literal["render", "target"] = "render",
) -> BufferSpec:
    return BufferSpec(name, tuple(components), required, resolution, low, high, tolerance, meaning)


# Order here is the order buffers are written in and reported in.
BUFFERS: dict[str, BufferSpec] = {
    spec.name: spec
    for spec in (
        # name, components, required, low, high, tolerance, meaning[, resolution]
        _spec("color", "RGB", True, 0.0, None, 0.0, "noisy linear HDR radiance, 1 sample per pixel"),
        _spec("albedo", "RGB", True, 0.0, 1.0, 1e-3, "diffuse albedo"),
        _spec("specular_albedo", "RGB", False, 0.0, 1.0, 1e-3, "approximate specular reflectance"),
        _spec("diffuse", "RGB", False, 0.0, None, 0.0, "color from paths whose first-hit lobe is diffuse"),
        _spec("specular", "RGB", False, 0.0, None, 0.0, "color from paths whose first-hit lobe is specular"),
        # Unit length is checked separately (where depth > 0), which also bounds the components.
        _spec("normal", "XYZ", True, None, None, 0.0, "world-space shading normal"),
        _spec("depth", "Z", True, 0.0, None, 0.0, "distance from the camera centre to the first hit"),
        _spec("roughness", "Y", False, 0.0, 1.0, 1e-3, "surface roughness, 1 for purely diffuse"),
        _spec("motion", "XY", True, None, None, 0.0, "offset to the previous frame's position, pixels"),
        _spec("reference", "RGB", False, 0.0, None, 0.0, "converged radiance at target resolution", "target"),
        _spec("reference_albedo", "RGB", False, 0.0, 1.0, 1e-3, "box-filtered diffuse albedo at target resolution",
              "target"),
        _spec("reference_specular_albedo", "RGB", False, 0.0, 1.0, 1e-3,
              "box-filtered specular albedo at target resolution", "target"),
    )
}

# Render-resolution buffers that are fields of FrameBundle (everything except the references).
RENDER_BUFFERS: tuple[str, ...] = tuple(name for name, spec in BUFFERS.items() if spec.resolution == "render")

# Target-resolution buffer -> the FrameBundle field holding it as a dict of scale -> array ("reference" ->
# "references"), in BUFFERS order. Every scale of the albedo references must also have a radiance reference.
TARGET_FIELDS: dict[str, str] = {name: f"{name}s" for name, spec in BUFFERS.items() if spec.resolution == "target"}

JITTER_LIMIT = 0.5
NORMAL_LENGTH_TOLERANCE = 1e-2  # half-float storage of normals is good to about 1e-3
LOBE_SPLIT_TOLERANCE = 1e-3  # |diffuse + specular - color| <= tol * (1 + color)


class FrameError(ValueError):
    """A frame that breaks the format; names the source (usually a file), the buffer and the problem.

    ``buffer`` is a buffer name from BUFFERS, a header attribute name (e.g. "jitter"), or None when the
    problem concerns the whole source (file not found, not an EXR).
    """

    def __init__(self, source: str, buffer: str | None, problem: str) -> None:
        # Passing every field to Exception keeps the error picklable (Celery ships errors across processes).
        super().__init__(source, buffer, problem)
        self.source = source
        self.buffer = buffer
        self.problem = problem

    def __str__(self) -> str:
        if self.buffer is None:
            return f"{self.source}: {self.problem}"
        kind = "buffer" if self.buffer in BUFFERS else "attribute"
        return f"{self.source}: {kind} '{self.buffer}': {self.problem}"


class FrameValidationError(FrameError):
    """The frame's contents break a convention (shape, range, NaN, unit length, ...)."""


@dataclass(eq=False)  # element-wise array comparison has no single truth value
class FrameBundle:
    color: np.ndarray  # (H, W, 3) float32, noisy linear HDR radiance >= 0
    albedo: np.ndarray  # (H, W, 3) in [0, 1]
    normal: np.ndarray  # (H, W, 3) unit length where depth > 0
    depth: np.ndarray  # (H, W) >= 0, 0 where nothing is hit
    motion: np.ndarray  # (H, W, 2) render-resolution pixels, prev = p + motion
    jitter: tuple[float, float]  # each in [-0.5, 0.5]
    frame_index: int = 0
    sequence: str = ""
    camera_cut: bool = False  # True on the first frame after a camera cut: history must be dropped
    diffuse: np.ndarray | None = None  # (H, W, 3), given together with specular or not at all
    specular: np.ndarray | None = None
    specular_albedo: np.ndarray | None = None  # (H, W, 3)
    roughness: np.ndarray | None = None  # (H, W)
    references: dict[int, np.ndarray] = field(default_factory=dict)  # scale -> (H*s, W*s, 3)
    # Box-filtered albedos at the target resolution, only at scales that have a reference: scale -> (H*s, W*s, 3)
    reference_albedos: dict[int, np.ndarray] = field(default_factory=dict)
    reference_specular_albedos: dict[int, np.ndarray] = field(default_factory=dict)

    @property
    def height(self) -> int:
        return int(self.color.shape[0])

    @property
    def width(self) -> int:
        return int(self.color.shape[1])

    @property
    def resolution(self) -> tuple[int, int]:
        """Render resolution as (width, height), the order image sizes are written in ("640x360")."""
        return self.width, self.height

    @property
    def scales(self) -> tuple[int, ...]:
        """Reference scales present, ascending."""
        return tuple(sorted(self.references))

    def reference(self, scale: int) -> np.ndarray:
        return self._target_buffer("reference", scale)

    def reference_albedo(self, scale: int) -> np.ndarray:
        return self._target_buffer("reference_albedo", scale)

    def reference_specular_albedo(self, scale: int) -> np.ndarray:
        return self._target_buffer("reference_specular_albedo", scale)

    def target_buffers(self, scale: int) -> dict[str, np.ndarray]:
        """The target-resolution buffers present at ``scale``, in BUFFERS order (empty if none)."""
        buffers = {name: getattr(self, attribute).get(scale) for name, attribute in TARGET_FIELDS.items()}
        return {name: array for name, array in buffers.items() if array is not None}

    def _target_buffer(self, name: str, scale: int) -> np.ndarray:
        by_scale = getattr(self, TARGET_FIELDS[name])
        try:
            return by_scale[scale]
        except KeyError:
            present = ", ".join(str(s) for s in sorted(by_scale)) or "none"
            raise KeyError(
                f"frame {self.frame_index} of sequence '{self.sequence}' has no {name} at scale {scale} "
                f"(scales present: {present})"
            ) from None

    def render_buffers(self) -> dict[str, np.ndarray]:
        """The render-resolution buffers present, in BUFFERS order."""
        buffers = {name: getattr(self, name) for name in RENDER_BUFFERS}
        return {name: array for name, array in buffers.items() if array is not None}


def box_downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """Mean over factor x factor pixel blocks: a box-filtered reference at 1/factor the resolution."""
    height, width = image.shape[:2]
    if height % factor or width % factor:
        raise ValueError(f"image of {width}x{height} pixels does not divide into {factor}x{factor} blocks")
    blocks = image.reshape(height // factor, factor, width // factor, factor, *image.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def validate_frame(frame: FrameBundle, source: str, *, sanitizable: bool = False) -> FrameBundle:
    """Check ``frame`` against every convention; raise FrameValidationError naming ``source`` on the first break.

    ``sanitizable``: for live input that ``model.io.sanitize.sanitize_frame`` repairs next (inference sessions): NaN,
    Inf and out-of-range values (negative radiance, albedo or roughness outside [0, 1], negative depth, a jitter
    that is not finite or outside its range) pass; everything a repair cannot fix is still checked: buffers,
    shapes, types, unit-length normals and diffuse + specular == color on the pixels that are finite.

    Returns the frame with every array float32 and C-contiguous (arrays already so are reused, the rest
    copied), jitter as a tuple of two floats and frame_index as an int. The input frame is not modified.
    """
    buffers = _float32_buffers(frame, source)
    targets: dict[str, dict[int, np.ndarray]] = {}
    for name, attribute in TARGET_FIELDS.items():
        _check_type(attribute, getattr(frame, attribute), dict, "a dict of scale -> array", source)
        targets[name] = _float32_targets(name, getattr(frame, attribute), source)
    _check_target_scales_have_references(targets, source)

    height, width = _check_color_shape(buffers["color"], source)
    for name, array in buffers.items():
        _check_shape(name, array, (height, width), source)
    for name, by_scale in targets.items():
        for scale, array in by_scale.items():
            _check_target_shape(name, scale, array, (height, width), source)

    named_arrays = list(buffers.items()) + [
        (name, array) for name, by_scale in targets.items() for array in by_scale.values()
    ]
    if not sanitizable:
        for name, array in named_arrays:
            _check_finite(name, array, source)
        for name, array in named_arrays:
            _check_range(BUFFERS[name], array, source)

    _check_normals_unit_length(buffers["normal"], buffers["depth"], source)
    _check_lobe_split(buffers["color"], buffers.get("diffuse"), buffers.get("specular"), source)
    jitter = _checked_jitter(frame.jitter, source, sanitizable)
    frame_index = _checked_frame_index(frame.frame_index, source)
    _check_type("sequence", frame.sequence, str, "a string", source)
    _check_type("camera_cut", frame.camera_cut, (bool, np.bool_), "a bool", source)

    return dataclasses.replace(
        frame,
        **buffers,
        **{TARGET_FIELDS[name]: by_scale for name, by_scale in targets.items()},
        jitter=jitter,
        frame_index=frame_index,
        camera_cut=bool(frame.camera_cut),
    )


def _float32_buffers(frame: FrameBundle, source: str) -> dict[str, np.ndarray]:
    buffers: dict[str, np.ndarray] = {}
    for name in RENDER_BUFFERS:
        value = getattr(frame, name)
        if value is None:
            if BUFFERS[name].required:
                raise FrameValidationError(source, name, "required buffer is missing")
            continue
        buffers[name] = _float32_array(name, value, source)
    return buffers


def _float32_targets(name: str, by_scale: dict, source: str) -> dict[int, np.ndarray]:
    converted: dict[int, np.ndarray] = {}
    for scale, array in by_scale.items():
        # bool is an Integral too, but True as a scale is surely a mistake.
        if not isinstance(scale, numbers.Integral) or isinstance(scale, (bool, np.bool_)) or scale < 1:
            raise FrameValidationError(source, name, f"scale {scale!r} is not a positive integer")
        converted[int(scale)] = _float32_array(name, array, source)
    return dict(sorted(converted.items()))


def _check_target_scales_have_references(targets: dict[str, dict[int, np.ndarray]], source: str) -> None:
    # Training pairs each albedo target with the radiance target of its scale; one alone is a broken frame.
    reference_scales = targets["reference"].keys()
    for name, by_scale in targets.items():
        missing = [scale for scale in by_scale if scale not in reference_scales]
        if missing:
            present = ", ".join(str(s) for s in reference_scales) or "none"
            raise FrameValidationError(
                source,
                name,
                f"at scale {missing[0]} has no radiance reference at that scale (reference scales present: {present})",
            )


def _float32_array(name: str, value, source: str) -> np.ndarray:
    try:
        return np.ascontiguousarray(value, dtype=np.float32)
    except (TypeError, ValueError) as error:
        raise FrameValidationError(source, name, f"is not a numeric array ({error})") from None


def _shape_text(shape: tuple[int, ...]) -> str:
    return f"{shape[1]}x{shape[0]}" if len(shape) >= 2 else str(shape)


def _check_color_shape(color: np.ndarray, source: str) -> tuple[int, int]:
    if color.ndim != 3 or color.shape[2] != 3:
        raise FrameValidationError(source, "color", f"shape {color.shape} is not (H, W, 3)")
    if color.shape[0] == 0 or color.shape[1] == 0:
        raise FrameValidationError(source, "color", f"shape {color.shape} has no pixels")
    return color.shape[0], color.shape[1]


def _expected_shape_text(spec: BufferSpec) -> str:
    return "(H, W)" if spec.is_scalar else f"(H, W, {len(spec.components)})"


def _check_channels(spec: BufferSpec, array: np.ndarray, source: str) -> None:
    if spec.is_scalar:
        if array.ndim != 2:
            raise FrameValidationError(source, spec.name, f"shape {array.shape} is not {_expected_shape_text(spec)}")
    elif array.ndim != 3 or array.shape[2] != len(spec.components):
        raise FrameValidationError(source, spec.name, f"shape {array.shape} is not {_expected_shape_text(spec)}")


def _check_shape(name: str, array: np.ndarray, render_hw: tuple[int, int], source: str) -> None:
    _check_channels(BUFFERS[name], array, source)
    if array.shape[:2] != render_hw:
        raise FrameValidationError(
            source,
            name,
            f"resolution {_shape_text(array.shape)} does not match color's {_shape_text(render_hw)} (WxH)",
        )


def _check_target_shape(
    name: str, scale: int, array: np.ndarray, render_hw: tuple[int, int], source: str
) -> None:
    _check_channels(BUFFERS[name], array, source)
    expected = (render_hw[0] * scale, render_hw[1] * scale)
    if array.shape[:2] != expected:
        raise FrameValidationError(
            source,
            name,
            f"at scale {scale} has resolution {_shape_text(array.shape)}, expected "
            f"{_shape_text(expected)} (WxH: {scale} x the render resolution {_shape_text(render_hw)})",
        )


def _pixel_mask(element_mask: np.ndarray) -> np.ndarray:
    """Per-pixel flag: true where any component is flagged."""
    return element_mask if element_mask.ndim == 2 else element_mask.any(axis=2)


def _pixel_of_element(array: np.ndarray, flat_index: int) -> tuple[int, int]:
    """(x, y) of the pixel holding element ``flat_index`` of an (H, W) or (H, W, C) array."""
    y, x = np.unravel_index(flat_index, array.shape)[:2]
    return int(x), int(y)


def _check_finite(name: str, array: np.ndarray, source: str) -> None:
    # Fast path: min and max propagate NaN and expose Inf, without the per-pixel masks below (which cost
    # ~10x more, since bool reductions over a 3-long last axis are slow in NumPy).
    if math.isfinite(float(array.min())) and math.isfinite(float(array.max())):
        return
    bad = _pixel_mask(~np.isfinite(array))
    y, x = np.unravel_index(int(np.argmax(bad)), bad.shape)  # argmax of a bool mask: first True
    raise FrameValidationError(
        source, name, f"{int(bad.sum())} pixels are not finite (NaN or Inf), first at pixel ({x}, {y})"
    )


def _check_range(spec: BufferSpec, array: np.ndarray, source: str) -> None:
    low = -math.inf if spec.low is None else spec.low - spec.tolerance
    high = math.inf if spec.high is None else spec.high + spec.tolerance
    # -0.0 >= 0.0 holds, so a signed zero from rounding passes the radiance check.
    if array.min() >= low and array.max() <= high:  # fast path, as in _check_finite
        return
    excess = np.maximum(low - array, array - high)
    bad = _pixel_mask(excess > 0)
    worst = int(np.argmax(excess))
    value = float(array.flat[worst])
    x, y = _pixel_of_element(array, worst)
    count = int(bad.sum())
    if spec.low == 0.0 and spec.high is None:
        problem = f"{count} pixels are negative (lowest {value:.6g} at pixel ({x}, {y}))"
    else:
        bounds = f"[{-math.inf if spec.low is None else spec.low:g}, {math.inf if spec.high is None else spec.high:g}]"
        problem = f"{count} pixels are outside {bounds} (worst {value:.6g} at pixel ({x}, {y}))"
    raise FrameValidationError(source, spec.name, problem)


def normal_lengths(normal: np.ndarray) -> np.ndarray:
    """|n| per pixel of (H, W, 3) normals: faster than np.linalg.norm(axis=2), which every live frame would pay
    twice (the lossy-normal repair and this check)."""
    return np.sqrt(np.einsum("ijk,ijk->ij", normal, normal))


def _check_normals_unit_length(normal: np.ndarray, depth: np.ndarray, source: str) -> None:
    # Only where something was hit: background pixels carry (0, 0, 0).
    # Non-finite pixels are _check_finite's (or, for sanitizable input, the sanitizer's) business.
    length = normal_lengths(normal)
    error = np.where((depth > 0) & np.isfinite(length), np.abs(length - 1.0), 0.0)
    bad = error > NORMAL_LENGTH_TOLERANCE
    if bad.any():
        worst = int(np.argmax(error))
        x, y = _pixel_of_element(error, worst)
        raise FrameValidationError(
            source,
            "normal",
            f"{int(bad.sum())} pixels are not unit length (worst |n| = {float(length.flat[worst]):.3g} "
            f"at pixel ({x}, {y})); normals must be unit length where depth > 0",
        )


def _check_lobe_split(
    color: np.ndarray, diffuse: np.ndarray | None, specular: np.ndarray | None, source: str
) -> None:
    if diffuse is None and specular is None:
        return
    if specular is None:
        raise FrameValidationError(source, "specular", "is missing but diffuse is given (give both or neither)")
    if diffuse is None:
        raise FrameValidationError(source, "diffuse", "is missing but specular is given (give both or neither)")
    # Relative to 1 + color: tight for bright pixels, absolute 1e-3 near black; half storage stays inside it.
    with np.errstate(invalid="ignore"):  # Inf - Inf in sanitizable input: such pixels are not compared
        excess = np.abs(diffuse + specular - color) - LOBE_SPLIT_TOLERANCE * (1.0 + color)
    excess = np.where(np.isfinite(excess), excess, 0.0)
    if excess.max() > 0:
        bad = _pixel_mask(excess > 0)
        worst = int(np.argmax(excess))
        x, y = _pixel_of_element(color, worst)
        difference = float(diffuse.flat[worst] + specular.flat[worst] - color.flat[worst])
        raise FrameValidationError(
            source,
            "diffuse",
            f"diffuse + specular differs from color at {int(bad.sum())} pixels "
            f"(worst difference {difference:.6g} at pixel ({x}, {y}))",
        )


def _checked_jitter(jitter, source: str, sanitizable: bool = False) -> tuple[float, float]:
    try:
        jitter_x, jitter_y = (float(value) for value in jitter)
    except (TypeError, ValueError):
        raise FrameValidationError(source, "jitter", f"{jitter!r} is not a pair of numbers") from None
    if sanitizable:
        return jitter_x, jitter_y
    if not (math.isfinite(jitter_x) and math.isfinite(jitter_y)):
        raise FrameValidationError(source, "jitter", f"({jitter_x}, {jitter_y}) is not finite")
    if max(abs(jitter_x), abs(jitter_y)) > JITTER_LIMIT:
        raise FrameValidationError(
            source, "jitter", f"({jitter_x:g}, {jitter_y:g}) is outside [-{JITTER_LIMIT}, {JITTER_LIMIT}]"
        )
    return jitter_x, jitter_y


def _checked_frame_index(frame_index, source: str) -> int:
    if not isinstance(frame_index, numbers.Integral) or isinstance(frame_index, (bool, np.bool_)):
        raise FrameValidationError(source, "frame_index", f"{frame_index!r} is not an integer")
    if frame_index < 0:
        raise FrameValidationError(source, "frame_index", f"{frame_index} is negative")
    return int(frame_index)


def _check_type(name: str, value, expected: type | tuple[type, ...], description: str, source: str) -> None:
    if not isinstance(value, expected):
        raise FrameValidationError(source, name, f"{value!r} is not {description}")
