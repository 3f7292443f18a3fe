"""The session stream's binary messages (GET /sessions/{id}/stream, a WebSocket): pack and unpack, NumPy only.

The wire format belongs to the client side: the client (client.stream) and the server
(service.http.routes.session_stream) both import it, and it imports neither torch nor the model library, so a
renderer that streams frames needs NumPy only. Every binary message, either way, is

    offset 0   4 bytes  magic b"DNST"
    offset 4   uint8    protocol version, 1
    offset 5   uint8    kind: 1 a frame (client -> server), 2 an output (server -> client)
    offset 6   uint16   0 (reserved)
    offset 8   uint32   N: length of the JSON header in bytes (little-endian, as every number here)
    offset 12  N bytes  the JSON header, UTF-8 (padded with spaces so the arrays start at a multiple of 16)
    offset 12 + N       the arrays: raw little-endian float16 or float32, planar, buffer after buffer in the
                        header's order; nothing after them

The fields of a frame's and of an output's header, for clients in other languages: docs/service.md, "Streaming
over a WebSocket".
"""

from __future__ import annotations

import json
import struct
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from client.frames import BUFFER_COMPONENTS, REQUIRED_BUFFERS, Frame

MAGIC = b"DNST"
VERSION = 1
FRAME, OUTPUT = 1, 2  # message kinds
PRELUDE = struct.Struct("<4sBBHI")  # magic, version, kind, reserved, JSON header length: 12 bytes
ALIGNMENT = 16  # the arrays start at a multiple of this (the JSON header is padded with spaces)
DTYPES: dict[str, np.dtype] = {"float16": np.dtype("<f2"), "float32": np.dtype("<f4")}
# Render-resolution buffers a frame may carry (the frame bundle's, client.frames.BUFFER_COMPONENTS); the required
# ones are client.frames.REQUIRED_BUFFERS.
STREAM_BUFFERS: tuple[str, ...] = tuple(BUFFER_COMPONENTS)
FRAME_FIELDS = frozenset({"frame_index", "width", "height", "dtype", "buffers", "jitter", "camera_cut",
                          "output_dtype"})
_KIND_NAMES = {FRAME: "frame", OUTPUT: "output"}


class StreamMessageError(ValueError):
    """A message that breaks the protocol. ``code``: ``invalid_message`` (not a message of this protocol, or a
    malformed header) or ``invalid_frame`` (the arrays do not match the header; a required buffer is missing), as
    the server answers it; ``details`` says more where there is more to say."""

    def __init__(self, message: str, code: str = "invalid_message", details: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.code = code
        self.details = details


class StreamFrameTooLarge(StreamMessageError):
    """A frame message declaring more pixels than the server's limit (code ``frame_too_large``)."""


@dataclass(frozen=True)
class StreamFrame:
    """A frame message unpacked: each buffer a read-only view of the message, (C, H, W) or (H, W) for one
    component, in the dtype it was sent in; ``planes`` all of them, (channels, H, W) in ``buffers``' order."""

    frame_index: int | None
    width: int
    height: int
    dtype: str
    buffers: dict[str, np.ndarray]
    jitter: tuple[float, float]
    camera_cut: bool = False
    output_dtype: str = "float32"
    planes: np.ndarray | None = field(default=None, repr=False)

    def hwc(self, name: str) -> np.ndarray:
        """Buffer ``name`` as the frame bundle holds it: (H, W, C) or (H, W), a view (no copy)."""
        planes = self.buffers[name]
        return planes if planes.ndim == 2 else planes.transpose(1, 2, 0)


@dataclass(frozen=True)
class StreamOutput:
    """An output message unpacked: ``image`` (H, W, 3) float32 (a copy, held as R, G, B planes in memory, as the
    session's own output is), ``header`` as sent."""

    image: np.ndarray
    header: dict[str, Any] = field(repr=False)

    @property
    def frame_index(self) -> int:
        return self.header["frame_index"]


# --- packing ---------------------------------------------------------------------------------------------


def _components(name: str) -> int:
    return len(BUFFER_COMPONENTS[name])


def _prelude(kind: int, header: dict[str, Any]) -> bytes:
    text = json.dumps(header, separators=(",", ":"), allow_nan=False).encode()
    text += b" " * (-(PRELUDE.size + len(text)) % ALIGNMENT)
    return PRELUDE.pack(MAGIC, VERSION, kind, 0, len(text)) + text


def _pack(kind: int, header: dict[str, Any], arrays: list[tuple[np.ndarray, int]], height: int, width: int,
          dtype: np.dtype) -> bytes:
    """The message: prelude, header, then each (H, W, C) / (H, W) array written planar (one copy, converting)."""
    prelude = _prelude(kind, header)
    plane = height * width * dtype.itemsize
    message = bytearray(len(prelude) + sum(components for _, components in arrays) * plane)
    message[:len(prelude)] = prelude
    offset = len(prelude)
    for array, components in arrays:
        target = np.frombuffer(message, dtype, components * height * width, offset)
        if components == 1:
            target.reshape(height, width)[...] = array
        else:
            target.reshape(components, height, width)[...] = np.moveaxis(array, -1, 0)
        offset += components * plane
    return bytes(message)


def _dtype_name(dtype: str, what: str) -> np.dtype:
    if dtype not in DTYPES:
        raise ValueError(f"{what} must be one of {', '.join(DTYPES)}, got {dtype!r}")
    return DTYPES[dtype]


def encode_frame(buffers: Mapping[str, np.ndarray], *, frame_index: int | None, jitter: tuple[float, float],
                 camera_cut: bool = False, dtype: str = "float32", output_dtype: str = "float32") -> bytes:
    """A frame message from frame-bundle buffers ((H, W, C) or (H, W) arrays, as model.io.frames.FrameBundle holds
    them; None values are left out), in STREAM_BUFFERS order. ValueError for an unknown buffer or a shape that
    does not fit the color's."""
    target = _dtype_name(dtype, "dtype")
    _dtype_name(output_dtype, "output_dtype")
    present = {name: np.asarray(array) for name, array in buffers.items() if array is not None}
    unknown = sorted(set(present) - set(STREAM_BUFFERS))
    if unknown:
        raise ValueError(f"unknown buffer(s) {', '.join(unknown)}; a frame carries {', '.join(STREAM_BUFFERS)}")
    if "color" not in present:
        raise ValueError("a frame needs its color buffer")
    height, width = present["color"].shape[:2]
    names = [name for name in STREAM_BUFFERS if name in present]
    for name in names:
        expected = (height, width) if _components(name) == 1 else (height, width, _components(name))
        if present[name].shape != expected:
            raise ValueError(f"buffer '{name}' is {present[name].shape}, expected {expected}")
    header = {"frame_index": None if frame_index is None else int(frame_index), "width": int(width),
              "height": int(height), "dtype": dtype, "buffers": names,
              "jitter": [float(jitter[0]), float(jitter[1])], "camera_cut": bool(camera_cut),
              "output_dtype": output_dtype}
    return _pack(FRAME, header, [(present[name], _components(name)) for name in names], height, width, target)


def encode_bundle(frame, *, dtype: str = "float32", output_dtype: str = "float32",
                  frame_index: int | None | bool = True, buffers: Iterable[str] | None = None) -> bytes:
    """A frame message of a client.frames.Frame or a model.io.frames.FrameBundle (its render-resolution buffers;
    references are never sent).
    ``frame_index``: True sends the frame's own, None leaves it to the session (its next frame), an int sends it.
    ``buffers``: send only these of the frame's buffers (the session's method's, GET /sessions/{id}: model.buffers;
    required ones are sent anyway), None: all it has."""
    index = frame.frame_index if frame_index is True else frame_index
    wanted = set(STREAM_BUFFERS if buffers is None else buffers) | set(REQUIRED_BUFFERS)
    names = [name for name in STREAM_BUFFERS if name in wanted]
    held = frame.buffers if isinstance(frame, Frame) else {name: getattr(frame, name, None) for name in names}
    return encode_frame({name: held.get(name) for name in names}, frame_index=index,
                        jitter=frame.jitter, camera_cut=frame.camera_cut, dtype=dtype, output_dtype=output_dtype)


def encode_output(image: np.ndarray, *, dtype: str = "float32", **header: Any) -> bytes:
    """An output message: ``image`` (H, W, 3) as R, G, B planes in ``dtype``; ``header`` the fields besides width,
    height and dtype (frame_index, server_ms, inference_ms, history, sanitized_pixels, ...)."""
    target = _dtype_name(dtype, "dtype")
    height, width = image.shape[:2]
    fields = {"frame_index": header.pop("frame_index"), "width": int(width), "height": int(height), "dtype": dtype,
              **header}
    return _pack(OUTPUT, fields, [(image, 3)], height, width, target)


# --- unpacking -------------------------------------------------------------------------------------------


def _unpack(data: bytes, kind: int) -> tuple[dict[str, Any], int]:
    """(the JSON header, the offset of the arrays) of a message of ``kind``; StreamMessageError otherwise."""
    data = memoryview(data)
    if len(data) < PRELUDE.size:
        raise StreamMessageError(f"the message is {len(data)} bytes, shorter than the {PRELUDE.size}-byte prelude "
                                 f"(magic {MAGIC.decode()}, version, kind, reserved, header length)")
    magic, version, got, _, length = PRELUDE.unpack_from(data)
    if magic != MAGIC:
        raise StreamMessageError(f"the message starts with {bytes(magic)!r}, not the magic {MAGIC!r}: not a frame "
                                 f"of this protocol")
    if version != VERSION:
        raise StreamMessageError(f"protocol version {version} is not supported; this server speaks version "
                                 f"{VERSION}", "unsupported_version", {"supported": [VERSION]})
    if got != kind:
        raise StreamMessageError(f"message kind {got} ({_KIND_NAMES.get(got, 'unknown')}) where a "
                                 f"{_KIND_NAMES[kind]} (kind {kind}) was expected")
    end = PRELUDE.size + length
    if end > len(data):
        raise StreamMessageError(f"the header length is {length} bytes but only {len(data) - PRELUDE.size} follow "
                                 f"the prelude")
    try:
        header = json.loads(bytes(data[PRELUDE.size:end]))
    except (UnicodeDecodeError, ValueError) as error:
        raise StreamMessageError(f"the header is not JSON: {error}") from None
    if not isinstance(header, dict):
        raise StreamMessageError(f"the header is a JSON {type(header).__name__}, not an object")
    return header, end


def _int_field(header: dict[str, Any], name: str, low: int) -> int:
    value = header.get(name)
    if not isinstance(value, int) or isinstance(value, bool) or value < low:
        raise StreamMessageError(f"header field '{name}' is {value!r}; expected an integer >= {low}")
    return value


def _dtype_field(header: dict[str, Any], name: str, default: str | None = None) -> str:
    value = header.get(name, default)
    if value not in DTYPES:
        raise StreamMessageError(f"header field '{name}' is {value!r}; expected one of {', '.join(DTYPES)}")
    return value


def _buffers_field(header: dict[str, Any]) -> list[str]:
    names = header.get("buffers")
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        raise StreamMessageError(f"header field 'buffers' is {names!r}; expected a list of buffer names")
    unknown = [name for name in names if name not in STREAM_BUFFERS]
    if unknown:
        raise StreamMessageError(f"unknown buffer(s) {', '.join(map(repr, unknown))} in 'buffers'; a frame carries "
                                 f"{', '.join(STREAM_BUFFERS)}", details={"buffers": list(STREAM_BUFFERS)})
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise StreamMessageError(f"buffer(s) {', '.join(repeated)} listed more than once in 'buffers'")
    missing = [name for name in REQUIRED_BUFFERS if name not in names]
    if missing:
        raise StreamMessageError(f"required buffer '{missing[0]}' is missing: 'buffers' must name "
                                 f"{', '.join(REQUIRED_BUFFERS)} (and may name "
                                 f"{', '.join(n for n in STREAM_BUFFERS if n not in REQUIRED_BUFFERS)})",
                                 "invalid_frame", {"buffer": missing[0], "problem": "missing"})
    return names


def _jitter_field(header: dict[str, Any]) -> tuple[float, float]:
    value = header.get("jitter")
    if (not isinstance(value, list) or len(value) != 2
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        raise StreamMessageError(f"header field 'jitter' is {value!r}; expected [x, y], two numbers")
    return float(value[0]), float(value[1])


def decode_frame(data: bytes, *, max_pixels: int | None = None) -> StreamFrame:
    """Unpack a frame message (views of ``data``, no copy); StreamMessageError naming what is wrong. ``max_pixels``:
    a frame of more pixels is refused (code frame_too_large) before its arrays are looked at."""
    header, offset = _unpack(data, FRAME)
    unknown = sorted(set(header) - FRAME_FIELDS)
    if unknown:
        raise StreamMessageError(f"unknown header field(s) {', '.join(unknown)}; a frame's header has "
                                 f"{', '.join(sorted(FRAME_FIELDS))}")
    index = header.get("frame_index")
    frame_index = None if index is None else _int_field(header, "frame_index", 0)
    width, height = _int_field(header, "width", 1), _int_field(header, "height", 1)
    if max_pixels is not None and width * height > max_pixels:
        raise StreamFrameTooLarge(f"the frame declares {width}x{height} = {width * height} pixels; the limit is "
                                 f"{max_pixels} pixels per frame", "frame_too_large",
                                 {"pixels": width * height, "limit_pixels": max_pixels})
    dtype = _dtype_field(header, "dtype")
    output_dtype = _dtype_field(header, "output_dtype", "float32")
    names = _buffers_field(header)
    jitter = _jitter_field(header)
    camera_cut = header.get("camera_cut", False)
    if not isinstance(camera_cut, bool):
        raise StreamMessageError(f"header field 'camera_cut' is {camera_cut!r}; expected true or false")

    itemsize = DTYPES[dtype].itemsize
    counts = {name: _components(name) * width * height for name in names}
    expected = sum(counts.values()) * itemsize
    if len(data) - offset != expected:
        layout = " + ".join(f"{name} {_components(name)}" for name in names)
        raise StreamMessageError(
            f"the arrays are {len(data) - offset} bytes; the header declares {width}x{height} pixels of "
            f"{layout} = {sum(counts.values()) // (width * height)} {dtype} planes = {expected} bytes",
            "invalid_frame", {"received_bytes": len(data) - offset, "expected_bytes": expected})
    planes = np.frombuffer(data, DTYPES[dtype], sum(counts.values()), offset).reshape(-1, height, width)
    buffers, first = {}, 0
    for name in names:
        components = _components(name)
        buffers[name] = planes[first] if components == 1 else planes[first:first + components]
        first += components
    return StreamFrame(frame_index, width, height, dtype, buffers, jitter, camera_cut, output_dtype, planes)


def decode_output(data: bytes) -> StreamOutput:
    """Unpack an output message: the (H, W, 3) float32 image and the header; StreamMessageError if it is none."""
    header, offset = _unpack(data, OUTPUT)
    width, height = _int_field(header, "width", 1), _int_field(header, "height", 1)
    dtype = _dtype_field(header, "dtype")
    expected = 3 * width * height * DTYPES[dtype].itemsize
    if len(data) - offset != expected:
        raise StreamMessageError(f"the output's arrays are {len(data) - offset} bytes; {width}x{height} RGB "
                                 f"{dtype} is {expected}", "invalid_frame")
    planes = np.frombuffer(data, DTYPES[dtype], 3 * width * height, offset).reshape(3, height, width)
    return StreamOutput(planes.transpose(1, 2, 0).astype(np.float32), header)

