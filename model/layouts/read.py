"""Reading one renderer EXR in a layout: channels gathered from every part, converted, validated.

Three modes, for three kinds of input:

- ``strict`` (uploads of stored data): values must be valid as they are; only unused channels are tolerated.
- ``import`` (``denoiser import``, a conversion that writes new files): normals off unit length by lossy
  compression (DWAA, B44) are renormalised, and reported.
- ``live`` (inference sessions): as ``import``, plus NaN, Inf and out-of-range values pass (the session repairs
  them, ``model.io.sanitize``) and a missing jitter attribute reads as 0 (the pixel centre), reported.

Whatever the mode, channels the layout does not use are ignored and listed in ``LayoutFrame.ignored_channels``
(less those the layout's ``ignore`` patterns expect), and a missing frame-index attribute leaves
``LayoutFrame.frame_index_given`` false: the caller decides what it means (the next frame, the file's position).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np
import OpenEXR

from model.io.exr import REFERENCE_PART_PATTERN, FrameFormatError, open_exr, open_exr_bytes, part_planes
from model.io.frames import BUFFERS, RENDER_BUFFERS, TARGET_FIELDS, FrameBundle, FrameValidationError, validate_frame
from model.layouts.convert import depth_to_bundle, motion_to_bundle, normals_to_world, renormalise_normals
from model.layouts.layout import Layout

Mode = Literal["strict", "import", "live"]
_FOV_IN_TEXT = re.compile(r"fov_y_degrees\s*=\s*([0-9.eE+-]+)")
_JITTER_IN_TEXT = re.compile(r"jitter\s*=\s*([0-9.eE+-]+)\s*,\s*([0-9.eE+-]+)")
_LISTED_CHANNELS = 12  # how many of a file's channels an error message lists


@dataclass(frozen=True)
class LayoutFrame:
    """A frame read in a layout, and what reading it involved."""

    frame: FrameBundle
    ignored_channels: tuple[str, ...] = ()  # present in the file, unused by the layout, not expected by it
    repairs: tuple[str, ...] = ()  # e.g. "normal: 12 pixels renormalised (worst |n| = 0.97)"
    frame_index_given: bool = True


@dataclass
class _Channels:
    """Every channel of a file: the render-resolution planes (all parts merged), the reference parts' planes by
    scale, the headers (first part first) and the channels of parts that could not be merged."""

    planes: dict[str, np.ndarray]
    reference_planes: dict[int, dict[str, np.ndarray]]
    headers: list[dict]
    unmergeable: list[str]


def read_layout_frame(path: str | os.PathLike, layout: Layout, *, mode: Mode = "strict",
                      fov_y_degrees: float | None = None, max_pixels: int | None = None,
                      max_decoded_bytes: int | None = None, reserve: Callable[[int], None] | None = None
                      ) -> LayoutFrame:
    """Read the EXR at ``path`` in ``layout``; FrameError naming the file on any problem.

    ``fov_y_degrees`` (planar depth only) overrides the layout's field of view and the header's. Before any pixel is
    decoded: ``max_pixels``, FrameTooLarge (a FrameError) when the headers declare more
    (``model.io.exr.check_declared_pixels``); ``max_decoded_bytes``, DecodeTooLarge when decoding the whole file
    would take more (``model.io.exr.check_decoded_bytes``); a required buffer none of whose channels the headers
    declare is refused; then ``reserve(decoded_bytes)`` (a memory budget, which may refuse)."""
    return _read(open_exr(path, max_pixels=max_pixels, max_decoded_bytes=max_decoded_bytes,
                          before_decode=_header_check(layout, str(path), reserve)),
                 str(path), layout, mode, fov_y_degrees)


def read_layout_frame_bytes(data: bytes, layout: Layout, source: str = "<bytes>", *, mode: Mode = "strict",
                            fov_y_degrees: float | None = None, max_pixels: int | None = None,
                            max_decoded_bytes: int | None = None, reserve: Callable[[int], None] | None = None,
                            read_references: bool = True) -> LayoutFrame:
    """``read_layout_frame`` for an EXR held in memory (a request body). ``read_references=False``: the reference
    parts (``reference_x<scale>``) are left out before decoding and before the size checks (a session's read)."""
    return _read(open_exr_bytes(data, source, max_pixels=max_pixels, max_decoded_bytes=max_decoded_bytes,
                                before_decode=_header_check(layout, source, reserve),
                                skip_reference_parts=not read_references),
                 source, layout, mode, fov_y_degrees)


def _header_check(layout: Layout, source: str, reserve: Callable[[int], None] | None):
    """Refuses, from the headers, a frame that lacks a required buffer (the bindings decode every channel of a file,
    so a file of nothing but unused channels would otherwise be decoded whole first); then ``reserve``."""
    def check(headers: list, decoded_bytes: int) -> None:
        declared: dict[str, None] = {}
        for index, part in enumerate(headers):
            match = REFERENCE_PART_PATTERN.fullmatch(part.name() or "") if index else None
            if match is not None and int(match.group(1)) >= 2:
                continue
            declared.update((channel.name, None) for channel in part.header.get("channels", ()))
        for buffer in RENDER_BUFFERS:
            alternatives = layout.channels.get(buffer, ())
            if BUFFERS[buffer].required and not any(all(name in declared for name in names)
                                                    for names in alternatives):
                if any(name in declared for names in alternatives for name in names):
                    continue  # a partial buffer: the read names the channels it lacks
                raise _missing(buffer, layout, declared, source)
        if reserve is not None:
            reserve(decoded_bytes)
    return check


def read_layout_reference(path: str | os.PathLike, layout: Layout, *,
                          max_pixels: int | None = None) -> dict[str, np.ndarray]:
    """A high-sample render of a frame in ``layout`` as target buffers: its colour is the ``reference``, its
    albedos (when the layout reads them) the ``reference_albedo`` and ``reference_specular_albedo``.
    ``max_pixels``: the frames' limit, which a reference render (at up to 2x) may exceed 4 times."""
    source = str(path)
    channels = _gather(open_exr(path, max_pixels=max_pixels, reference_render=True), source)
    targets = {}
    for buffer, target in (("color", "reference"), ("albedo", "reference_albedo"),
                           ("specular_albedo", "reference_specular_albedo")):
        array = _assemble(buffer, layout, channels.planes, source)
        if array is None and buffer == "color":
            raise _missing(buffer, layout, channels.planes, source, what="the reference's colour")
        if array is not None:
            targets[target] = array
    return targets


# --- gathering channels ----------------------------------------------------------------------------------


def _gather(exr: OpenEXR.File, source: str) -> _Channels:
    if not exr.parts:
        raise FrameFormatError(source, None, "EXR file has no parts")
    planes: dict[str, np.ndarray] = {}
    references: dict[int, dict[str, np.ndarray]] = {}
    unmergeable: list[str] = []
    size = None
    for index, part in enumerate(exr.parts):
        if part.type() not in (OpenEXR.scanlineimage, OpenEXR.tiledimage):
            unmergeable.extend(f"{name} (part '{part.name()}', {part.type().name})" for name in part.channels)
            continue
        part_channels = part_planes(part)
        match = REFERENCE_PART_PATTERN.fullmatch(part.name()) if index else None
        if match is not None and int(match.group(1)) >= 2:
            references[int(match.group(1))] = part_channels
            continue
        shapes = {plane.shape[:2] for plane in part_channels.values()}
        if size is None and shapes:
            size = next(iter(shapes))
        if shapes - {size}:  # another resolution (a preview, a subsampled AOV): nothing a frame can use
            unmergeable.extend(f"{name} (part '{part.name()}', another resolution)" for name in part_channels)
            continue
        planes.update(part_channels)
    return _Channels(planes, references, [part.header for part in exr.parts], unmergeable)


def _assemble(buffer: str, layout: Layout, planes: dict[str, np.ndarray], source: str,
              used: set[str] | None = None) -> np.ndarray | None:
    """The buffer from the first of the layout's alternatives whose channels are all present; None if none is;
    FrameFormatError for a partial one (some channels of an alternative but not all) or non-float pixels."""
    alternatives = layout.channels.get(buffer, ())
    for names in alternatives:
        if all(name in planes for name in names):
            for name in names:
                if planes[name].dtype not in (np.float16, np.float32):
                    raise FrameFormatError(source, buffer, f"channel '{name}' holds {planes[name].dtype}, not float "
                                                           f"or half")
            if used is not None:
                used.update(names)
            if BUFFERS[buffer].is_scalar:
                return planes[names[0]].astype(np.float32)
            return np.stack([planes[name] for name in names], axis=-1, dtype=np.float32)
    for names in alternatives:
        present = [name for name in names if name in planes]
        if present:
            missing = [name for name in names if name not in planes]
            raise FrameFormatError(source, buffer, f"partial buffer: has {', '.join(present)} but lacks "
                                                   f"{', '.join(missing)} (layout '{layout.name}')")
    return None


def _missing(buffer: str, layout: Layout, planes: dict, source: str, what: str = "") -> FrameFormatError:
    names = sorted(planes)
    listed = ", ".join(names[:_LISTED_CHANNELS]) + (f" and {len(names) - _LISTED_CHANNELS} more"
                                                    if len(names) > _LISTED_CHANNELS else "")
    return FrameFormatError(
        source, buffer,
        f"required buffer is missing{' (' + what + ')' if what else ''}: layout '{layout.name}' reads it from "
        f"{layout.channel_names(buffer) or 'no channels'}, and the file has none of them (it has: {listed or 'none'}); "
        f"choose the layout of the renderer that wrote it (built-in: denoiser, blender-cycles, generic) or map "
        f"these channels in a layout file" + (f"; {layout.hint}" if layout.hint else ""))


# --- header attributes -----------------------------------------------------------------------------------


def _attribute(headers: list[dict], name: str):
    for header in headers:
        if name in header:
            return header[name]
    return None


def _frame_index(headers: list[dict], layout: Layout, source: str) -> int | None:
    name = layout.sample.frame_index_attribute
    value = _attribute(headers, name)
    if value is None:
        return None
    if isinstance(value, str) and value.strip().isdigit():  # Blender writes 'Frame' as text, e.g. '001'
        return int(value)
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, int) or isinstance(value, bool) or value < 0:
        raise FrameFormatError(source, "frame_index", f"attribute '{name}' is {value!r}, not a frame number")
    return value


def _jitter(headers: list[dict], layout: Layout, mode: Mode, source: str) -> tuple[tuple[float, float], str | None]:
    """(jitter, the repair to report or None)."""
    if layout.sample.jitter == "centre":
        return (0.0, 0.0), None
    name = layout.sample.jitter_attribute
    value = _attribute(headers, name)
    if isinstance(value, str):  # a text attribute, e.g. Blender's metadata note "fov_y_degrees=39.6 jitter=0.25,-0.1"
        match = _JITTER_IN_TEXT.search(value)
        value = _text_jitter(match, source, name) if match else None
    if value is None:
        if layout.sample.jitter == "header-or-centre":
            return (0.0, 0.0), None
        if mode == "live":
            return (0.0, 0.0), f"jitter: no '{name}' attribute, read as 0 (samples at the pixel centres)"
        raise FrameFormatError(
            source, "jitter",
            f"missing header attribute '{name}' (the sub-pixel sample offset, 2 floats); if the renderer samples "
            f"the pixel centres, read the file with a layout whose sample.jitter is \"centre\" or "
            f"\"header-or-centre\" (built-in: generic, blender-cycles), else write the attribute")
    jitter = np.asarray(value)
    if jitter.shape != (2,) or not np.issubdtype(jitter.dtype, np.number):
        raise FrameFormatError(source, "jitter", f"attribute '{name}' is {value!r}, not a pair of numbers")
    return (float(jitter[0]), float(jitter[1])), None


def _text_jitter(match: re.Match, source: str, name: str) -> tuple[float, float]:
    try:
        return float(match.group(1)), float(match.group(2))
    except ValueError:
        raise FrameFormatError(source, "jitter", f"attribute '{name}' has {match.group(0)!r}, not "
                                                 f"'jitter=X,Y' with two numbers") from None


def _fov_y(headers: list[dict], layout: Layout, override: float | None, source: str) -> float:
    if override is not None:
        return override
    attribute = layout.depth.fov_y_attribute
    value = _attribute(headers, attribute) if attribute else None
    if isinstance(value, str):  # a text attribute, e.g. Blender's metadata note "fov_y_degrees=39.6"
        match = _FOV_IN_TEXT.search(value)
        value = float(match.group(1)) if match else (float(value) if _is_number(value) else None)
    if isinstance(value, (int, float)) and 0 < value < 180:
        return float(value)
    if layout.depth.fov_y_degrees is not None:
        return layout.depth.fov_y_degrees
    where = f"its header attribute '{attribute}' " if attribute else ""
    raise FrameFormatError(
        source, "depth",
        f"layout '{layout.name}' stores planar depth, which needs the vertical field of view to become the distance "
        f"along each ray, and {where or 'the file '}gives none; give it (denoiser import --fov-y DEGREES, or "
        f"depth.fov_y_degrees in a layout file)"
        + (" or stamp the note 'fov_y_degrees=...' into the render's metadata (Blender: Output Properties > "
           "Metadata > Note)" if attribute == "Note" else "") + _fov_from_lens(headers))


def _fov_from_lens(headers: list[dict]) -> str:
    """For an error without a field of view: what Blender's 'Lens' stamp (focal length in mm, when enabled) gives
    with its default 36 mm sensor fitted to the wider side. Only a suggestion: the header holds no sensor size."""
    lens, window = _attribute(headers, "Lens"), _attribute(headers, "dataWindow")
    try:
        focal = float(str(lens).removesuffix("mm").strip())
        width, height = (int(high - low + 1) for low, high in zip(*window))
    except (TypeError, ValueError):
        return ""
    if not (focal > 0 and width > 0 and height > 0):
        return ""
    half_wide = 18.0 / focal  # tan of half the field of view across the wider side
    fov_y = 2 * math.degrees(math.atan(half_wide * min(1.0, height / width)))
    return (f"; the header's Lens is {focal:g} mm: with Blender's default 36 mm sensor (Sensor Fit Auto) that is "
            f"--fov-y {fov_y:.4f} for this {width}x{height} image, if the camera's sensor is the default")


def _is_number(text: str) -> bool:
    try:
        return math.isfinite(float(text))
    except ValueError:
        return False


def _int_attribute(headers: list[dict], name: str, source: str) -> int:
    value = _attribute(headers, name)
    if value is None:
        return 0
    if not isinstance(value, int):
        raise FrameFormatError(source, name, f"{value!r} is not an integer")
    return value


# --- the frame -------------------------------------------------------------------------------------------


def _read(exr: OpenEXR.File, source: str, layout: Layout, mode: Mode, fov_override: float | None) -> LayoutFrame:
    channels = _gather(exr, source)
    used: set[str] = set()
    buffers: dict[str, np.ndarray] = {}
    for buffer in RENDER_BUFFERS:
        array = _assemble(buffer, layout, channels.planes, source, used)
        if array is None and BUFFERS[buffer].required:
            raise _missing(buffer, layout, channels.planes, source)
        if array is not None:
            buffers[buffer] = array
    targets: dict[str, dict[int, np.ndarray]] = {name: {} for name in TARGET_FIELDS}
    for name in TARGET_FIELDS:
        array = _assemble(name, layout, channels.planes, source, used)
        if array is not None:
            targets[name][1] = array
    for scale, planes in channels.reference_planes.items():
        for name in TARGET_FIELDS:
            array = _assemble(name, layout, planes, source)
            if array is not None:
                targets[name][scale] = array
        if scale not in targets["reference"]:
            raise FrameFormatError(source, "reference", f"part 'reference_x{scale}' has no reference channels")

    repairs: list[str] = []
    jitter, jitter_repair = _jitter(channels.headers, layout, mode, source)
    if jitter_repair:
        repairs.append(jitter_repair)
    buffers.update(_converted(buffers, layout, channels.headers, jitter, fov_override, source))
    repairs += _renormalised(buffers, mode, source)

    frame_index = _frame_index(channels.headers, layout, source)
    sequence = _attribute(channels.headers, "sequence")
    frame = FrameBundle(
        **buffers, jitter=jitter, frame_index=0 if frame_index is None else frame_index,
        sequence=sequence if isinstance(sequence, str) else "",
        camera_cut=bool(_int_attribute(channels.headers, "camera_cut", source)),
        **{TARGET_FIELDS[name]: by_scale for name, by_scale in targets.items()},
    )
    frame = validate_frame(frame, source, sanitizable=mode == "live")
    ignored = sorted(name for name in channels.planes if name not in used and not layout.is_ignored(name))
    ignored += [name for name in channels.unmergeable if not layout.is_ignored(name.split(" (")[0])]
    return LayoutFrame(frame, tuple(ignored), tuple(repairs), frame_index is not None)


def read_bundle_buffers(buffers: dict[str, np.ndarray], *, jitter: tuple[float, float], frame_index: int,
                        camera_cut: bool = False, source: str = "<buffers>", mode: Mode = "live") -> LayoutFrame:
    """A frame given as arrays in the frame bundle's own conventions rather than as an EXR (the session stream's
    frames): (H, W, C) or (H, W) arrays of any float dtype, render-resolution buffers only. The same conversions,
    repairs and checks as reading an EXR of the ``denoiser`` layout in ``mode``, so a frame reaches a session the
    same way whichever transport carried it; FrameError naming ``source`` on any problem."""
    from model.layouts.builtin import BUILTIN_LAYOUTS

    layout = BUILTIN_LAYOUTS["denoiser"]
    for buffer in RENDER_BUFFERS:
        if BUFFERS[buffer].required and buffers.get(buffer) is None:
            raise FrameFormatError(source, buffer, "required buffer is missing")
    # As _assemble gives them: float32, C-contiguous (H, W, C).
    arrays = {name: np.ascontiguousarray(array, dtype=np.float32) for name, array in buffers.items()
              if array is not None}
    arrays.update(_converted(arrays, layout, [], jitter, None, source))
    repairs = _renormalised(arrays, mode, source)
    frame = FrameBundle(**arrays, jitter=jitter, frame_index=frame_index, camera_cut=camera_cut)
    return LayoutFrame(validate_frame(frame, source, sanitizable=mode == "live"), (), tuple(repairs))


def _renormalised(buffers: dict[str, np.ndarray], mode: Mode, source: str) -> list[str]:
    """Normals off unit length by lossy compression renormalised in ``buffers`` (refused in strict mode); the
    repair to report, if any."""
    normal, count, worst = renormalise_normals(buffers["normal"], buffers["depth"])
    if count and mode == "strict":  # stored data is not repaired, but the refusal says what to do
        raise FrameValidationError(
            source, "normal", f"{count} pixels are off unit length by up to {abs(worst - 1):.3g} (|n| = {worst:.3g}), "
                              f"as lossy compression (DWAA, B44) leaves them; store normals losslessly (ZIP, PIZ) or "
                              f"convert with denoiser import, which renormalises them")
    if not count:
        return []
    buffers["normal"] = normal
    return [f"normal: {count} pixels renormalised (worst |n| = {worst:.3g}; lossy compression?)"]


def _converted(buffers: dict[str, np.ndarray], layout: Layout, headers: list[dict], jitter: tuple[float, float],
               fov_override: float | None, source: str) -> dict[str, np.ndarray]:
    """Motion, depth and normal in the frame bundle's conventions."""
    converted = {"motion": motion_to_bundle(buffers["motion"], layout.motion)}
    fov = _fov_y(headers, layout, fov_override, source) if layout.depth.kind == "planar" else None
    converted["depth"] = depth_to_bundle(buffers["depth"], layout.depth, fov, jitter)
    normal = buffers["normal"]
    if layout.normal.space == "view":
        name = layout.normal.view_matrix_attribute
        matrix = _attribute(headers, name)
        if matrix is None or np.asarray(matrix).size != 16:
            raise FrameFormatError(source, "normal", f"layout '{layout.name}' has view-space normals, which need the "
                                                     f"camera's 4x4 '{name}' header attribute to become world space; "
                                                     f"the file has none (write it, or export world-space normals)")
        normal = normals_to_world(normal, np.asarray(matrix))
    # Where nothing is hit the frame bundle's normal is 0, whatever the renderer wrote there.
    converted["normal"] = np.where((converted["depth"] > 0)[..., None], normal, 0.0).astype(np.float32)
    return converted
