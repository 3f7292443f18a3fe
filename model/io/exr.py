"""One frame bundle = one EXR file (OpenEXR 3.x Python bindings).

``write_frame`` writes part 0, named "render", with every render-resolution buffer (channels named by
``frames.BUFFERS``: ``color.R``, ``normal.X``, ``depth.Z``, ...) and the scale-1 references, and one more part per
reference scale s > 1, named ``reference_x{s}``, at (H*s, W*s). Header attributes: ``jitter`` (V2d: two doubles, so
Python floats round-trip exactly), ``frame_index``, ``sequence``, ``scale`` (the largest reference scale) and
``camera_cut``. Multi-part EXR requires every part to share one displayWindow, so all parts carry the
render-resolution display window; the larger parts' data windows extend past it. ``read_frame`` also accepts
single-part files from other renderers; ``jitter`` is required there too, the other attributes have defaults.
With ``half=True`` every channel is stored as IEEE half (11 significant bits; values above 65504 are refused rather
than stored as Inf). The layout and the precision half storage keeps: docs/frame-format.md, "EXR layout".
"""

from __future__ import annotations

import io
import os
import re
import struct
import uuid
from pathlib import Path
from typing import Callable

import numpy as np
import OpenEXR

from model.io.frames import (
    BUFFERS,
    RENDER_BUFFERS,
    TARGET_FIELDS,
    FrameBundle,
    FrameError,
    FrameValidationError,
    validate_frame,
)

RENDER_PART = "render"
REFERENCE_PART_PATTERN = re.compile(r"reference_x(\d+)")
EXR_MAGIC = b"\x76\x2f\x31\x01"  # first 4 bytes of every OpenEXR file
HALF_MAX = float(np.finfo(np.float16).max)
INT32_MAX = 2**31 - 1  # EXR int attributes are 32-bit; the bindings silently store larger values as 0

# "color.R" -> ("color", 0): where each known channel goes.
CHANNEL_SLOTS: dict[str, tuple[str, int]] = {
    channel: (spec.name, component)
    for spec in BUFFERS.values()
    for component, channel in enumerate(spec.channels)
}


class FrameFormatError(FrameError):
    """The file is not a readable frame bundle EXR (missing, not EXR, truncated, wrong channels or header)."""


class FrameTooLarge(FrameFormatError):
    """The header declares more pixels than the reader's limit (found before any pixel is decoded)."""

    def __init__(self, source: str, problem: str, pixels: int, limit: int) -> None:
        super().__init__(source, None, problem)
        self.pixels = pixels
        self.limit = limit

    def __reduce__(self):  # picklable with the extra fields (Celery ships errors across processes)
        return (type(self), (self.source, self.problem, self.pixels, self.limit))


class DecodeTooLarge(FrameTooLarge):
    """The headers declare more decoded bytes than the reader's limit (found before any pixel is decoded);
    ``pixels`` holds those bytes."""


# Besides its render part, a frame's file may hold reference parts at a larger scale (a 2x reference has 4 times
# the render pixels) and, from another renderer, one part per render pass (Blender writes 6 for the passes
# blender-cycles reads): the whole file is bounded by the values it declares (pixels x channels over all parts), at
# most this many per pixel of the limit. A frame bundle with every buffer and 1x and 2x references declares 61 per
# render pixel, Blender's 6 passes 18.
MAX_VALUES_PER_PIXEL = 128
# A reference render of a frame in another renderer's layout (a references/ file, a high-sample render at the
# target resolution) may be at 2x: 4 times the render-pixel limit.
REFERENCE_RENDER_PIXEL_FACTOR = 4
# The bindings decode every part and channel of a file, whatever the reader uses, and their headers do not tell a
# channel's pixel type (it comes with the pixels): a decode is counted at 4 bytes a value (float and uint; half
# takes 2), an upper bound.
DECODED_BYTES_PER_VALUE = 4


def reference_part_name(scale: int) -> str:
    return f"reference_x{scale}"


def write_frame(path: str | os.PathLike, frame: FrameBundle, *, half: bool = False) -> Path:
    """Validate ``frame`` and write it to ``path`` atomically; return the path.

    The file is written under a temporary name in the same directory and renamed over ``path``, so a
    failed write (invalid frame, full disk, ...) leaves an existing file untouched and readers never see
    half a file.
    """
    path = Path(path)
    frame = validate_frame(frame, str(path))
    if frame.frame_index > INT32_MAX:
        raise FrameValidationError(str(path), "frame_index", f"{frame.frame_index} does not fit an EXR int")
    if half:
        _check_fits_half(frame, str(path))
    parts = _frame_parts(frame, half)
    # A unique hidden name that is not a *.exr, so directory scans never pick up a half-written frame.
    temporary = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        try:
            OpenEXR.File(parts).write(str(temporary))
        except RuntimeError as error:  # the bindings' only report of an unwritable path or full disk
            raise OSError(f"{path}: cannot write EXR ({error})") from None
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    return path


def read_frame(path: str | os.PathLike, *, sanitizable: bool = False, max_pixels: int | None = None,
               max_decoded_bytes: int | None = None) -> FrameBundle:
    """Read and validate one frame bundle; every error is a FrameError naming the file. ``sanitizable``: let NaN,
    Inf and out-of-range values through (``model.io.frames.validate_frame``), for frames a session repairs.
    ``max_pixels``: FrameTooLarge, from the header alone, for a render part above that many pixels (see
    ``check_declared_pixels``). ``max_decoded_bytes``: DecodeTooLarge, from the header alone, for a file whose
    decode would take more (``check_decoded_bytes``)."""
    source = str(path)
    return _frame_from_exr(_open_exr(Path(path), source, max_pixels, max_decoded_bytes=max_decoded_bytes), source,
                           sanitizable)


# Called with the headers and the bytes their decode will take, after the size checks and before the decode: a
# reader refuses there what the headers already tell (a missing buffer) or reserves the memory.
BeforeDecode = Callable[[list, int], None]


def open_exr(path: str | os.PathLike, *, max_pixels: int | None = None, reference_render: bool = False,
             max_decoded_bytes: int | None = None, before_decode: BeforeDecode | None = None) -> OpenEXR.File:
    """Every part of an EXR file with its pixels (FrameFormatError naming the file if it cannot be read).
    ``max_pixels``: FrameTooLarge from the headers first, before any pixel is decoded (``check_declared_pixels``,
    whose ``reference_render`` this passes on); ``max_decoded_bytes``: DecodeTooLarge likewise
    (``check_decoded_bytes``); then ``before_decode(headers, decoded_bytes)``."""
    return _open_exr(Path(path), str(path), max_pixels, reference_render, max_decoded_bytes, before_decode)


def open_exr_bytes(data: bytes, source: str = "<bytes>", *, max_pixels: int | None = None,
                   max_decoded_bytes: int | None = None, before_decode: BeforeDecode | None = None,
                   skip_reference_parts: bool = False) -> OpenEXR.File:
    """``open_exr`` for an EXR held in memory. ``skip_reference_parts``: parts named ``reference_x<scale>`` (scale
    >= 2) are left out before anything is decoded (``select_parts``), for a reader that never uses them."""
    if data[: len(EXR_MAGIC)] != EXR_MAGIC:
        problem = "empty" if not data else "not an OpenEXR file (wrong magic number)"
        raise FrameFormatError(source, None, problem)
    if skip_reference_parts:
        names = [_part_name(part) for part in _read_headers(io.BytesIO(data), source)]
        keep = [index for index, name in enumerate(names) if index == 0 or not _is_reference_part(name)]
        if len(keep) < len(names):
            data = select_parts(data, keep) or data
    return _read_exr(lambda: io.BytesIO(data), source, max_pixels, False, max_decoded_bytes, before_decode)


def _is_reference_part(name: str) -> bool:
    match = REFERENCE_PART_PATTERN.fullmatch(name)
    return match is not None and int(match.group(1)) >= 2


# The EXR file layout (openexr.com, "OpenEXR File Layout"): version flags, then for a multi-part file the headers
# (attributes up to an empty name, the list ended by an empty header), one offset table per part (chunkCount
# 64-bit offsets) and the chunks, each led by its part number.
_MULTIPART = 0x1000
_NON_IMAGE = 0x800


def select_parts(data: bytes, keep: list[int]) -> bytes | None:
    """The bytes of a multi-part EXR holding only the parts ``keep`` (indices, in file order), their compressed
    chunks copied as they are, so the parts left out are never decoded; None where the file is not a multi-part
    scanline file this can read (the caller then reads it whole). The bindings can only decode a whole file."""
    try:
        version = struct.unpack_from("<i", data, 4)[0]
        if not version & _MULTIPART or version & _NON_IMAGE:
            return None
        position, headers = 8, []
        while data[position] != 0:  # a header: attributes (name, type, size, value) up to an empty name
            start, attributes = position, {}
            while data[position] != 0:
                name_end = data.index(b"\0", position)
                type_end = data.index(b"\0", name_end + 1)
                size = struct.unpack_from("<i", data, type_end + 1)[0]
                value_start = type_end + 5
                attributes[data[position:name_end]] = data[value_start:value_start + size]
                position = value_start + size
            position += 1
            headers.append((data[start:position], attributes))
        position += 1
        tables = []
        for _, attributes in headers:
            count = struct.unpack("<i", attributes[b"chunkCount"])[0]
            tables.append(struct.unpack_from(f"<{count}Q", data, position))
            position += 8 * count
        if any(headers[index][1].get(b"type") != b"scanlineimage" for index in keep):
            return None
        out = bytearray(data[:8])
        for index in keep:
            out += headers[index][0]
        out += b"\0"
        chunks_start = len(out) + 8 * sum(len(tables[index]) for index in keep)
        table_bytes, chunk_bytes = bytearray(), bytearray()
        for new_index, index in enumerate(keep):
            for offset in tables[index]:  # a scanline chunk: part number, first line, size, data
                if struct.unpack_from("<i", data, offset)[0] != index:
                    return None
                size = struct.unpack_from("<i", data, offset + 8)[0]
                end = offset + 12 + size
                if size < 0 or end > len(data):
                    return None
                table_bytes += struct.pack("<Q", chunks_start + len(chunk_bytes))
                chunk_bytes += struct.pack("<i", new_index) + data[offset + 4:end]
        return bytes(out + table_bytes + chunk_bytes)
    except (struct.error, IndexError, KeyError, ValueError):
        return None


def part_planes(part: OpenEXR.Part) -> dict[str, np.ndarray]:
    """Channel name -> (H, W) pixel plane of one part, whatever the channels are (other renderers' files)."""
    return dict(_planes(part))


# --- writing ---------------------------------------------------------------------------------------------


def _check_fits_half(frame: FrameBundle, source: str) -> None:
    arrays = list(frame.render_buffers().items()) + [
        item for scale in frame.scales for item in frame.target_buffers(scale).items()
    ]
    for name, array in arrays:
        too_large = int(np.count_nonzero(np.abs(array) > HALF_MAX))
        if too_large:
            raise FrameValidationError(
                source,
                name,
                f"{too_large} values exceed the largest half float ({HALF_MAX:g}); write with half=False",
            )


def _channel_arrays(spec_name: str, array: np.ndarray, half: bool) -> dict[str, np.ndarray]:
    """Split an (H, W[, C]) buffer into contiguous per-channel planes.

    The bindings write non-contiguous arrays (e.g. ``array[:, :, 1]``) as garbage without complaint, hence
    the explicit contiguous copies.
    """
    spec = BUFFERS[spec_name]
    dtype = np.float16 if half else np.float32
    planes = [array] if spec.is_scalar else [array[:, :, c] for c in range(len(spec.components))]
    return {channel: np.ascontiguousarray(plane, dtype=dtype) for channel, plane in zip(spec.channels, planes)}


def _part_header(render_width: int, render_height: int, attributes: dict,
                 compression=OpenEXR.ZIP_COMPRESSION) -> dict:
    display_window = (np.array([0, 0], np.int32), np.array([render_width - 1, render_height - 1], np.int32))
    return {
        "compression": compression,
        "type": OpenEXR.scanlineimage,
        "displayWindow": display_window,
        **attributes,
    }


def _frame_parts(frame: FrameBundle, half: bool, compression=OpenEXR.ZIP_COMPRESSION) -> list[OpenEXR.Part]:
    # OpenEXR.Part replaces the arrays in the dict it is given with Channel objects: build fresh dicts.
    render_channels: dict[str, np.ndarray] = {}
    for name, array in frame.render_buffers().items():
        render_channels.update(_channel_arrays(name, array, half))
    for name, array in frame.target_buffers(1).items():
        render_channels.update(_channel_arrays(name, array, half))
    render_attributes = {
        "jitter": np.array(frame.jitter, dtype=np.float64),  # float64 pair -> V2d; a tuple would become V2f
        "frame_index": frame.frame_index,
        "sequence": frame.sequence,
        "scale": max(frame.scales, default=1),
        "camera_cut": int(frame.camera_cut),
    }
    header = _part_header(frame.width, frame.height, render_attributes, compression)
    parts = [OpenEXR.Part(header, render_channels, RENDER_PART)]
    for scale in frame.scales:
        if scale == 1:
            continue
        header = _part_header(frame.width, frame.height, {"scale": scale}, compression)
        channels: dict[str, np.ndarray] = {}
        for name, array in frame.target_buffers(scale).items():
            channels.update(_channel_arrays(name, array, half))
        parts.append(OpenEXR.Part(header, channels, reference_part_name(scale)))
    return parts


# --- reading ---------------------------------------------------------------------------------------------


def _open_exr(path: Path, source: str, max_pixels: int | None = None, reference_render: bool = False,
              max_decoded_bytes: int | None = None, before_decode: BeforeDecode | None = None) -> OpenEXR.File:
    _check_exr_file(path, source)
    return _read_exr(lambda: str(path), source, max_pixels, reference_render, max_decoded_bytes, before_decode)


def _read_headers(target: str | io.BytesIO, source: str) -> list:
    # The bindings raise RuntimeError for unreadable headers and document nothing else: any failure of
    # this call means the file cannot be read.
    try:
        return OpenEXR.File(target, header_only=True).parts
    except Exception as error:
        raise FrameFormatError(source, None, f"unreadable or truncated EXR ({error})") from None


def _part_pixels(part) -> tuple[int, int]:
    """(width, height) of a part's data window, as its header declares it."""
    try:
        low, high = part.header["dataWindow"]
        return int(high[0]) - int(low[0]) + 1, int(high[1]) - int(low[1]) + 1
    except (KeyError, TypeError, ValueError, IndexError):
        return 0, 0  # no usable data window: the full read reports what is wrong with the file


def _part_name(part) -> str:
    try:
        return part.name() or ""
    except Exception:  # a header without a usable name: the full read reports what is wrong with the file
        return ""


def check_declared_pixels(parts: list, source: str, max_pixels: int, *, reference_render: bool = False) -> None:
    """FrameTooLarge when the headers declare a render part (the first part, and any other not named
    ``reference_x<scale>``: another renderer's pass parts) of more than ``max_pixels`` pixels, or all parts
    together more than MAX_VALUES_PER_PIXEL values (pixels x channels) per pixel of ``max_pixels``.
    ``reference_render``: the file is a reference render at the target resolution, whose parts may have
    REFERENCE_RENDER_PIXEL_FACTOR times the pixels. Compressed pixel data can declare any size (an all-zero
    2048x2048 frame compresses to about 200 KB), so this runs before anything is decoded, whatever the layout."""
    limit = max_pixels * (REFERENCE_RENDER_PIXEL_FACTOR if reference_render else 1)
    values = 0
    for index, part in enumerate(parts):
        width, height = _part_pixels(part)
        name = _part_name(part)
        if (index == 0 or not REFERENCE_PART_PATTERN.fullmatch(name)) and width * height > limit:
            where = f" in part '{name}'" if index else ""
            raise FrameTooLarge(source, f"declares {width}x{height} = {width * height} pixels{where}; the limit is "
                                        f"{limit} pixels per {'reference render' if reference_render else 'frame'}",
                                width * height, limit)
        try:
            channels = len(part.header.get("channels", ()))
        except (AttributeError, TypeError):
            channels = 0
        values += width * height * max(1, channels)
    if values > MAX_VALUES_PER_PIXEL * max_pixels:
        raise FrameTooLarge(source, f"declares {values} values (pixels x channels) in its {len(parts)} parts; the "
                                    f"limit is {MAX_VALUES_PER_PIXEL * max_pixels} ({MAX_VALUES_PER_PIXEL} per pixel "
                                    f"of the {max_pixels}-pixel frame limit)",
                            values, MAX_VALUES_PER_PIXEL * max_pixels)


def decoded_part_bytes(parts: list) -> list[tuple[str, int]]:
    """(part name, bytes its decode takes: pixels x channels x DECODED_BYTES_PER_VALUE) of each part, from the
    headers."""
    sizes = []
    for part in parts:
        width, height = _part_pixels(part)
        try:
            channels = len(part.header.get("channels", ()))
        except (AttributeError, TypeError):
            channels = 0
        sizes.append((_part_name(part), width * height * max(1, channels) * DECODED_BYTES_PER_VALUE))
    return sizes


def check_decoded_bytes(parts: list, source: str, max_bytes: int) -> int:
    """The bytes decoding every part takes (``decoded_part_bytes``); DecodeTooLarge naming them, the largest part
    and the limit when they pass ``max_bytes``."""
    sizes = decoded_part_bytes(parts)
    total = sum(size for _, size in sizes)
    if total > max_bytes:
        name, largest = max(sizes, key=lambda item: item[1])
        where = f"; its largest part, '{name or 'unnamed'}', {largest} bytes" if len(sizes) > 1 else ""
        raise DecodeTooLarge(source, f"decodes to {total} bytes (pixels x channels x {DECODED_BYTES_PER_VALUE} bytes "
                                     f"per value, all {len(sizes)} parts{where}); the limit is {max_bytes} bytes "
                                     f"per frame", total, max_bytes)
    return total


def check_frame_file_pixels(path: str | os.PathLike, max_pixels: int, source: str | None = None, *,
                            reference_render: bool = False, max_decoded_bytes: int | None = None) -> None:
    """``check_declared_pixels`` (and with ``max_decoded_bytes``, ``check_decoded_bytes``) for an EXR file, reading
    its headers only."""
    source = source or str(path)
    parts = _read_headers(str(path), source)
    check_declared_pixels(parts, source, max_pixels, reference_render=reference_render)
    if max_decoded_bytes is not None:
        check_decoded_bytes(parts, source, max_decoded_bytes)


def _read_exr(target: Callable[[], str | io.BytesIO], source: str, max_pixels: int | None = None,
              reference_render: bool = False, max_decoded_bytes: int | None = None,
              before_decode: BeforeDecode | None = None) -> OpenEXR.File:
    """Every part of the EXR at ``target()`` (a path, or a fresh stream per call) with its pixels; with
    ``max_pixels`` and ``max_decoded_bytes``, the headers are checked against them first (``check_declared_pixels``,
    ``check_decoded_bytes``), then ``before_decode`` runs."""
    parts = _read_headers(target(), source)
    part_count = len(parts)
    if max_pixels is not None:
        check_declared_pixels(parts, source, max_pixels, reference_render=reference_render)
    if max_decoded_bytes is not None:
        check_decoded_bytes(parts, source, max_decoded_bytes)
    if before_decode is not None:
        before_decode(parts, sum(size for _, size in decoded_part_bytes(parts)))
    exr = _read_coalesced(target, part_count)
    if exr is None:  # an unusual channel layout, or a damaged file: the plain read reports what is wrong
        try:
            exr = OpenEXR.File(target(), separate_channels=True)
        except Exception as error:
            raise FrameFormatError(source, None, f"unreadable or truncated EXR ({error})") from None
    # A part whose pixel data cannot be decoded (e.g. a truncated file) is not an error for the bindings:
    # they print a warning and leave the part out. Comparing with the header's part count catches it.
    if len(exr.parts) != part_count:
        raise FrameFormatError(
            source,
            None,
            f"unreadable or truncated EXR (pixel data of {part_count - len(exr.parts)} of {part_count} parts "
            f"could not be read)",
        )
    return exr


def _read_coalesced(target: Callable[[], str | io.BytesIO], part_count: int) -> OpenEXR.File | None:
    """The file read the bindings' default way, or None where that read fails or its channels are not exactly
    those the headers declare.

    By default the bindings decode a part in one pass and return each prefix's R, G, B[, A] channels as one
    interleaved (H, W, 3 or 4) array, e.g. ``color`` for color.R/G/B: several times faster than
    ``separate_channels=True`` for uncompressed files (one read per scanline instead of one per channel and
    scanline), and those arrays are the frame's buffers as they are. They refuse to coalesce channels of mixed
    pixel types; ``_planes`` names the others.
    """
    try:
        exr = OpenEXR.File(target())
        if len(exr.parts) != part_count:
            return None
        for part in exr.parts:
            declared = {channel.name for channel in part.header.get("channels", ())}
            if set(_planes(part)) != declared:
                return None
    except Exception:  # whatever this read cannot do, the plain read does or reports
        return None
    return exr


class _Planes(dict):
    """Channel name -> (H, W) plane of one part; ``interleaved`` maps the channel names of each array the bindings
    read as one (R, G, B[, A] in that order) to that array, whose planes the entries are views of."""

    def __init__(self) -> None:
        super().__init__()
        self.interleaved: dict[tuple[str, ...], np.ndarray] = {}


def _planes(part: OpenEXR.Part) -> _Planes:
    planes = _Planes()
    for key, channel in part.channels.items():
        pixels = channel.pixels
        if getattr(pixels, "ndim", None) == 3 and pixels.shape[2] in (3, 4):
            names = tuple(f"{key}.{component}" for component in "RGBA"[: pixels.shape[2]])
            planes.interleaved[names] = pixels
            planes.update((name, pixels[:, :, index]) for index, name in enumerate(names))
        else:
            planes[key] = pixels
    return planes


def _frame_from_exr(exr: OpenEXR.File, source: str, sanitizable: bool = False) -> FrameBundle:
    """The validated frame bundle an opened EXR holds (``read_frame`` and ``read_frame_bytes``)."""
    render_part, reference_parts = _split_parts(exr.parts, source)
    buffers, scale_one_targets = _render_buffers(render_part, source)
    targets: dict[str, dict[int, np.ndarray]] = {name: {} for name in TARGET_FIELDS}
    for name, array in scale_one_targets.items():
        targets[name][1] = array
    for scale, part in reference_parts.items():
        for name, array in _reference_part_buffers(part, source).items():
            targets[name][scale] = array
    header = render_part.header
    _check_scale_attribute(header, max(targets["reference"], default=1), source)
    frame = FrameBundle(
        **buffers,
        jitter=_jitter_attribute(header, source),
        frame_index=_int_attribute(header, "frame_index", 0, source),
        sequence=_string_attribute(header, "sequence", source),
        camera_cut=bool(_int_attribute(header, "camera_cut", 0, source)),
        **{TARGET_FIELDS[name]: by_scale for name, by_scale in targets.items()},
    )
    return validate_frame(frame, source, sanitizable=sanitizable)


def _split_parts(parts: list, source: str) -> tuple[OpenEXR.Part, dict[int, OpenEXR.Part]]:
    if not parts:
        raise FrameFormatError(source, None, "EXR file has no parts")
    references: dict[int, OpenEXR.Part] = {}
    for part in parts[1:]:
        name = part.name()
        match = REFERENCE_PART_PATTERN.fullmatch(name)
        if match is None or int(match.group(1)) < 2:
            raise FrameFormatError(
                source, None, f"unexpected part '{name}' (extra parts must be named reference_x<scale>, scale >= 2)"
            )
        scale = int(match.group(1))
        _check_part_storage(part, source)
        _check_scale_attribute(part.header, scale, source, part=name)
        references[scale] = part
    _check_part_storage(parts[0], source)
    return parts[0], dict(sorted(references.items()))


def _check_part_storage(part: OpenEXR.Part, source: str) -> None:
    if part.type() not in (OpenEXR.scanlineimage, OpenEXR.tiledimage):
        raise FrameFormatError(source, None, f"part '{part.name()}' is a {part.type().name}, not a flat image")


def _channel_pixels(part: OpenEXR.Part, source: str) -> _Planes:
    pixels = _planes(part)
    for key, channel in part.channels.items():
        if channel.xSampling != 1 or channel.ySampling != 1:
            raise FrameFormatError(source, None, f"channel '{key}' is subsampled; every channel must be full size")
    for name, plane in pixels.items():
        if plane.dtype not in (np.float16, np.float32):
            raise FrameFormatError(source, None, f"channel '{name}' holds {plane.dtype}, not float or half")
    unknown = sorted(name for name in pixels if name not in CHANNEL_SLOTS)
    if unknown:
        raise FrameFormatError(
            source, None, f"unknown channels in part '{part.name()}': {', '.join(unknown)}"
        )
    return pixels


def _assemble_buffer(buffer: str, pixels: _Planes, source: str) -> np.ndarray | None:
    """Stack a buffer's channel planes into one float32 array; None when none of its channels is present."""
    spec = BUFFERS[buffer]
    present = [channel for channel in spec.channels if channel in pixels]
    if not present:
        return None
    if len(present) != len(spec.channels):
        missing = [channel for channel in spec.channels if channel not in pixels]
        raise FrameFormatError(
            source, buffer, f"partial buffer: has {', '.join(present)} but lacks {', '.join(missing)}"
        )
    # One copy at most: the arrays the bindings return own their memory, so a float32 plane, or an interleaved
    # array of exactly the buffer's channels, is used as is; stacking converts half planes as it goes.
    if spec.is_scalar:
        return pixels[spec.channels[0]].astype(np.float32, copy=False)
    interleaved = pixels.interleaved.get(spec.channels)
    if interleaved is not None:
        return interleaved.astype(np.float32, copy=False)
    return np.stack([pixels[channel] for channel in spec.channels], axis=-1, dtype=np.float32)


def _render_buffers(part: OpenEXR.Part, source: str) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The render-resolution buffers and the scale-1 target buffers (name -> array) present in the part."""
    pixels = _channel_pixels(part, source)
    buffers = {}
    for name in RENDER_BUFFERS:
        array = _assemble_buffer(name, pixels, source)
        if array is None and BUFFERS[name].required:
            channels = ", ".join(BUFFERS[name].channels)
            raise FrameFormatError(source, name, f"required buffer is missing (no {channels} channels)")
        if array is not None:
            buffers[name] = array
    return buffers, _target_buffers(pixels, source)


def _target_buffers(pixels: _Planes, source: str) -> dict[str, np.ndarray]:
    buffers = {name: _assemble_buffer(name, pixels, source) for name in TARGET_FIELDS}
    return {name: array for name, array in buffers.items() if array is not None}


def _reference_part_buffers(part: OpenEXR.Part, source: str) -> dict[str, np.ndarray]:
    """The target buffers of one ``reference_x{s}`` part; the radiance reference is required there."""
    pixels = _channel_pixels(part, source)
    other = sorted(name for name in pixels if CHANNEL_SLOTS[name][0] not in TARGET_FIELDS)
    if other:
        allowed = ", ".join(f"{name}.{'/'.join(BUFFERS[name].components)}" for name in TARGET_FIELDS)
        raise FrameFormatError(source, None, f"part '{part.name()}' may hold only {allowed}, not {', '.join(other)}")
    buffers = _target_buffers(pixels, source)
    if "reference" not in buffers:
        raise FrameFormatError(source, "reference", f"part '{part.name()}' has no reference channels")
    return buffers


def _check_scale_attribute(header: dict, expected: int, source: str, part: str = RENDER_PART) -> None:
    if "scale" not in header:
        if part != RENDER_PART:
            raise FrameFormatError(source, "scale", f"missing header attribute in part '{part}'")
        return
    scale = header["scale"]
    if isinstance(scale, float) and scale.is_integer():
        scale = int(scale)
    if not isinstance(scale, int) or scale < 1:
        raise FrameFormatError(source, "scale", f"{scale!r} in part '{part}' is not a positive integer")
    if scale != expected:
        what = "the largest reference scale in the file" if part == RENDER_PART else "the scale in the part name"
        raise FrameFormatError(source, "scale", f"{scale} in part '{part}' does not match {expected}, {what}")


def _jitter_attribute(header: dict, source: str) -> tuple[float, float]:
    if "jitter" not in header:
        raise FrameFormatError(source, "jitter", "missing header attribute (sub-pixel sample offset, 2 floats)")
    jitter = np.asarray(header["jitter"])
    if jitter.shape != (2,) or not np.issubdtype(jitter.dtype, np.number):
        raise FrameFormatError(source, "jitter", f"{header['jitter']!r} is not a pair of numbers (V2f or V2d)")
    return float(jitter[0]), float(jitter[1])


def _int_attribute(header: dict, name: str, default: int, source: str) -> int:
    value = header.get(name, default)
    if not isinstance(value, int):
        raise FrameFormatError(source, name, f"{value!r} is not an integer")
    return value


def _string_attribute(header: dict, name: str, source: str) -> str:
    value = header.get(name, "")
    if not isinstance(value, str):
        raise FrameFormatError(source, name, f"{value!r} is not a string")
    return value


# --- in-memory frames and output images (the session API) ------------------------------------------------
#
# The REST service receives frame bundles as request bodies and answers with one image, so it reads and writes
# EXR from bytes rather than files. Output images are one-part, float32 R/G/B files: what any EXR viewer opens.

IMAGE_CHANNELS = ("R", "G", "B")


def encode_frame_exr(frame: FrameBundle, *, half: bool = False, compression=OpenEXR.ZIP_COMPRESSION,
                     sanitizable: bool = False) -> bytes:
    """The bytes ``write_frame`` would write for ``frame`` (validated the same way), e.g. a request body.

    ``compression``: any lossless OpenEXR compression (ZIP, as ``write_frame``, by default); ``read_frame_bytes``
    reads them all. Uncompressed frames cost the writer and the reader far less CPU time than ZIP (the reader's
    one pass over them is the fastest read there is), for 1.5 to 3 times the bytes. ``sanitizable``: NaN, Inf and
    out-of-range values pass (``model.io.frames.validate_frame``), for a receiver that repairs them (a session).
    """
    source = "<frame>"
    frame = validate_frame(frame, source, sanitizable=sanitizable)
    if frame.frame_index > INT32_MAX:
        raise FrameValidationError(source, "frame_index", f"{frame.frame_index} does not fit an EXR int")
    if half:
        _check_fits_half(frame, source)
    stream = io.BytesIO()
    OpenEXR.File(_frame_parts(frame, half, compression)).write(stream)
    return stream.getvalue()


def read_frame_bytes(data: bytes, source: str = "<bytes>", *, sanitizable: bool = False,
                     max_pixels: int | None = None, max_decoded_bytes: int | None = None) -> FrameBundle:
    """``read_frame`` for a frame bundle held in memory; errors are FrameErrors naming ``source``.

    ``sanitizable``: let NaN, Inf and out-of-range values through (``model.io.frames.validate_frame``), for input that
    ``model.io.sanitize.sanitize_frame`` repairs next. ``max_pixels``, ``max_decoded_bytes``: as ``read_frame``."""
    if data[: len(EXR_MAGIC)] != EXR_MAGIC:
        problem = "empty" if not data else "not an OpenEXR file (wrong magic number)"
        raise FrameFormatError(source, None, problem)
    return _frame_from_exr(_read_exr(lambda: io.BytesIO(data), source, max_pixels, False, max_decoded_bytes), source,
                           sanitizable)


def _image_file(rgb: np.ndarray, attributes: dict | None, compression) -> OpenEXR.File:
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError(f"an RGB image must have shape (H, W, 3), got {rgb.shape}")
    # Contiguous float32 planes: the bindings write strided arrays as garbage (see _channel_arrays).
    channels = {name: np.ascontiguousarray(rgb[:, :, c], dtype=np.float32) for c, name in enumerate(IMAGE_CHANNELS)}
    header = {"compression": compression, "type": OpenEXR.scanlineimage, **(attributes or {})}
    return OpenEXR.File(header, channels)


def encode_image_exr(rgb: np.ndarray, attributes: dict | None = None,
                     compression=OpenEXR.NO_COMPRESSION) -> bytes:
    """One-part float32 R/G/B EXR of an (H, W, 3) image, as bytes; ``attributes`` go into the header.

    Uncompressed by default: on a local network, ZIP costs more CPU time per frame than it saves in transfer.
    """
    stream = io.BytesIO()
    _image_file(rgb, attributes, compression).write(stream)
    return stream.getvalue()


def write_image(destination: str | os.PathLike | io.IOBase, rgb: np.ndarray, attributes: dict | None = None,
                compression=OpenEXR.ZIP_COMPRESSION) -> None:
    """Write an (H, W, 3) image as a one-part float32 R/G/B EXR to a path (atomically) or a binary stream."""
    if isinstance(destination, (str, os.PathLike)):
        path = Path(destination)
        temporary = path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")
        try:
            try:
                _image_file(rgb, attributes, compression).write(str(temporary))
            except RuntimeError as error:
                raise OSError(f"{path}: cannot write EXR ({error})") from None
            os.replace(temporary, path)
        finally:
            temporary.unlink(missing_ok=True)
    else:
        _image_file(rgb, attributes, compression).write(destination)


def decode_image_exr(data: bytes, source: str = "<bytes>") -> np.ndarray:
    """The (H, W, 3) float32 R/G/B image of a one-part EXR (``encode_image_exr``'s output or any RGB file)."""
    if data[: len(EXR_MAGIC)] != EXR_MAGIC:
        raise FrameFormatError(source, None, "not an OpenEXR file (wrong magic number)")
    try:  # the bindings' default read: R, G, B as one interleaved array, decoded in one pass (see _read_coalesced)
        part = OpenEXR.File(io.BytesIO(data)).parts[0]
        arrays = [channel.pixels for channel in part.channels.values()]
        declared = {channel.name for channel in part.header.get("channels", ())}
        if declared == set(IMAGE_CHANNELS) and len(arrays) == 1 and arrays[0].shape[2:] == (3,):
            return arrays[0].astype(np.float32, copy=False)
    except Exception:  # mixed pixel types, more channels, a damaged file: the plain read below tells
        pass
    try:
        exr = OpenEXR.File(io.BytesIO(data), separate_channels=True)
    except Exception as error:
        raise FrameFormatError(source, None, f"unreadable or truncated EXR ({error})") from None
    if not exr.parts:
        raise FrameFormatError(source, None, "EXR file has no readable parts")
    channels = exr.parts[0].channels
    missing = [name for name in IMAGE_CHANNELS if name not in channels]
    if missing:
        raise FrameFormatError(source, None, f"not an RGB image: lacks channels {', '.join(missing)}")
    return np.stack([channels[name].pixels for name in IMAGE_CHANNELS], axis=-1, dtype=np.float32)


def is_image_exr(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a plain one-part R/G/B image (``write_image``'s output, or any renderer's beauty pass)
    rather than a frame bundle; reads the header only."""
    path = Path(path)
    _check_exr_file(path, str(path))
    parts = _read_headers(str(path), str(path))
    if len(parts) != 1:
        return False
    declared = {channel.name for channel in parts[0].header.get("channels", ())}
    return set(IMAGE_CHANNELS) <= declared and declared <= {*IMAGE_CHANNELS, "A"}


def _check_exr_file(path: Path, source: str) -> None:
    if not path.is_file():
        raise FrameFormatError(source, None, "is a directory, not a file" if path.is_dir() else "file not found")
    with path.open("rb") as file:
        if file.read(len(EXR_MAGIC)) != EXR_MAGIC:
            raise FrameFormatError(source, None, "not an OpenEXR file (wrong magic number)")
