"""Frames on the client side with NumPy and OpenEXR only: what a renderer plug-in needs, never torch.

- ``Frame`` / ``make_frame``: a frame's render-resolution buffers as arrays, (H, W, C) or (H, W), plus jitter,
  frame index, sequence name and camera cut; the server checks every convention (docs/frame-format.md).
- ``encode_frame_exr`` / ``read_frame_exr``: a frame bundle EXR (part "render", channels ``<buffer>.<component>``,
  what POST /sessions/{id}/frames takes); the reader keeps the render buffers and drops the references.
- ``encode_image_exr`` / ``decode_image_exr``: the float32 R/G/B EXR of an output; ``encode_png``: its 8-bit
  display encoding, ``clip(x, 0, 1) ** (1/2.2)`` (zlib, no imaging library).
- ``manifest_format``, ``sequence_frame_files``, ``renderer_frame_files``: which files of a folder are frames. Only a
  manifest.json whose ``format`` is this project's is read as one; a renderer's or a pipeline's own manifest and
  other files are left out and named.

The server reads frames with model.io.exr (strict checks); tests/client/test_frames.py holds the two to one format.
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import OpenEXR

from client.rest import FRAME_COMPRESSIONS

MANIFEST = "manifest.json"
SEQUENCE_FORMAT = "denoiser-sequence/1"
DATASET_FORMAT = "denoiser-dataset/1"
RENDER_PART = "render"
REFERENCES_FOLDER = "references"
# The render-resolution buffers of a frame bundle and their EXR channel suffixes, in the order they are written
# (model.io.frames.BUFFERS, less the references; a test keeps the two equal).
BUFFER_COMPONENTS: dict[str, str] = {"color": "RGB", "albedo": "RGB", "specular_albedo": "RGB", "diffuse": "RGB",
                                     "specular": "RGB", "normal": "XYZ", "depth": "Z", "roughness": "Y",
                                     "motion": "XY"}
REQUIRED_BUFFERS: tuple[str, ...] = ("color", "albedo", "normal", "depth", "motion")
EXR_MAGIC = b"\x76\x2f\x31\x01"


class FrameFileError(ValueError):
    """A file or array that is not a frame as the client can send it; the message names the source and problem."""


@dataclass(eq=False)  # element-wise array comparison has no single truth value
class Frame:
    """One frame's render-resolution buffers (float32; (H, W, C), or (H, W) for depth and roughness)."""

    buffers: dict[str, np.ndarray]
    jitter: tuple[float, float] = (0.0, 0.0)
    frame_index: int | None = None  # None: the session numbers it (its next frame)
    sequence: str = ""
    camera_cut: bool = False
    attributes: dict = field(default_factory=dict, repr=False)  # other header attributes, as read

    @property
    def height(self) -> int:
        return int(self.buffers["color"].shape[0])

    @property
    def width(self) -> int:
        return int(self.buffers["color"].shape[1])


def make_frame(*, color, albedo, normal, depth, motion, jitter=(0.0, 0.0), frame_index: int | None = None,
               sequence: str = "", camera_cut: bool = False, source: str = "<arrays>", **optional) -> Frame:
    """A Frame from a renderer's arrays; ``optional``: specular_albedo, diffuse, specular, roughness. A (H, W, 1)
    depth or roughness is accepted as (H, W). FrameFileError names a buffer of the wrong shape or an unknown one."""
    unknown = sorted(set(optional) - set(BUFFER_COMPONENTS))
    if unknown:
        raise FrameFileError(f"{source}: unknown buffer(s) {', '.join(unknown)}; a frame carries "
                             f"{', '.join(BUFFER_COMPONENTS)}")
    given = {"color": color, "albedo": albedo, "normal": normal, "depth": depth, "motion": motion,
             **{name: value for name, value in optional.items() if value is not None}}
    buffers = {}
    for name in BUFFER_COMPONENTS:
        if name not in given:
            continue
        array = np.asarray(given[name], dtype=np.float32)
        components = len(BUFFER_COMPONENTS[name])
        if components == 1 and array.ndim == 3 and array.shape[2] == 1:
            array = array[:, :, 0]
        buffers[name] = array
    height, width = buffers["color"].shape[:2] if buffers["color"].ndim == 3 else (0, 0)
    for name, array in buffers.items():
        components = len(BUFFER_COMPONENTS[name])
        expected = (height, width) if components == 1 else (height, width, components)
        if array.shape != expected or height == 0 or width == 0:
            raise FrameFileError(f"{source}: buffer '{name}' has shape {array.shape}, expected {expected}"
                                 if name != "color" or height else
                                 f"{source}: buffer 'color' has shape {array.shape}, expected (H, W, 3)")
    pair = np.asarray(jitter, dtype=np.float64)
    if pair.shape != (2,):
        raise FrameFileError(f"{source}: jitter {jitter!r} is not a pair of numbers")
    return Frame(buffers, (float(pair[0]), float(pair[1])), None if frame_index is None else int(frame_index),
                 sequence, bool(camera_cut))


def as_frame(frame) -> Frame:
    """A Frame as it is, or one of any object with the buffers as attributes (model.io.frames.FrameBundle)."""
    if isinstance(frame, Frame):
        return frame
    buffers = {name: getattr(frame, name) for name in BUFFER_COMPONENTS if getattr(frame, name, None) is not None}
    return make_frame(**buffers, jitter=frame.jitter, frame_index=getattr(frame, "frame_index", None),
                      sequence=getattr(frame, "sequence", ""), camera_cut=getattr(frame, "camera_cut", False),
                      source="<frame>")


def _compression(name: str):
    if name not in FRAME_COMPRESSIONS:
        raise ValueError(f"compression must be one of {', '.join(FRAME_COMPRESSIONS)}, got {name!r}")
    return getattr(OpenEXR, f"{'NO' if name == 'none' else name.upper()}_COMPRESSION")


def encode_frame_exr(frame, *, compression: str = "none") -> bytes:
    """A frame bundle EXR of ``frame`` (a Frame, or a FrameBundle) as bytes: one part "render", float32 channels."""
    frame = as_frame(frame)
    channels = {}
    for name, array in frame.buffers.items():
        planes = [array] if array.ndim == 2 else [array[:, :, c] for c in range(array.shape[2])]
        for component, plane in zip(BUFFER_COMPONENTS[name], planes):
            # Contiguous float32 planes: the bindings write strided arrays as garbage.
            channels[f"{name}.{component}"] = np.ascontiguousarray(plane, dtype=np.float32)
    header = {"compression": _compression(compression), "type": OpenEXR.scanlineimage,
              "displayWindow": (np.array([0, 0], np.int32), np.array([frame.width - 1, frame.height - 1], np.int32)),
              "jitter": np.array(frame.jitter, dtype=np.float64),  # float64 pair -> V2d (exact round trip)
              "sequence": frame.sequence, "scale": 1, "camera_cut": int(frame.camera_cut)}
    if frame.frame_index is not None:
        header["frame_index"] = int(frame.frame_index)
    stream = io.BytesIO()
    OpenEXR.File([OpenEXR.Part(header, channels, RENDER_PART)]).write(stream)
    return stream.getvalue()


def read_frame_exr(source: str | os.PathLike | bytes) -> Frame:
    """The render buffers and header of a frame bundle EXR (a path or bytes); references are left out. Values are
    not checked (the server does, and repairs NaN / Inf); a missing jitter reads as 0, as a session reads it.
    FrameFileError for a file that is not a frame bundle."""
    name = "<bytes>" if isinstance(source, (bytes, bytearray, memoryview)) else str(source)
    data = bytes(source) if name == "<bytes>" else Path(source).read_bytes()
    if data[:4] != EXR_MAGIC:
        raise FrameFileError(f"{name}: not an OpenEXR file (wrong magic number)")
    try:
        exr = OpenEXR.File(io.BytesIO(data), separate_channels=True)
    except Exception as error:
        raise FrameFileError(f"{name}: unreadable or truncated EXR ({error})") from None
    parts = exr.parts
    part = next((p for p in parts if p.name() == RENDER_PART), parts[0]) if parts else None
    if part is None:
        raise FrameFileError(f"{name}: the EXR has no parts")
    planes = {key: channel.pixels for key, channel in part.channels.items()}
    buffers = {}
    for buffer, components in BUFFER_COMPONENTS.items():
        keys = [f"{buffer}.{component}" for component in components]
        present = [key in planes for key in keys]
        if not any(present):
            continue
        if not all(present):
            raise FrameFileError(f"{name}: buffer '{buffer}' lacks channel(s) "
                                 f"{', '.join(k for k, p in zip(keys, present) if not p)}")
        arrays = [np.asarray(planes[key], dtype=np.float32) for key in keys]
        buffers[buffer] = arrays[0] if len(arrays) == 1 else np.stack(arrays, axis=-1)
    missing = [buffer for buffer in REQUIRED_BUFFERS if buffer not in buffers]
    if missing:
        raise FrameFileError(f"{name}: not a frame bundle: required buffer(s) {', '.join(missing)} missing "
                             f"(channels named <buffer>.<component>, docs/frame-format.md)")
    header = part.header
    # A live renderer's file may lack the jitter: a session reads it as 0 (docs/frame-format.md), so the client
    # sends 0 rather than refusing what the server would take.
    jitter = np.asarray(header.get("jitter", (0.0, 0.0)), dtype=np.float64).reshape(-1)
    if jitter.shape != (2,):
        raise FrameFileError(f"{name}: header attribute 'jitter' {header['jitter']!r} is not a pair of numbers")
    index = header.get("frame_index")
    frame = make_frame(**buffers, jitter=(float(jitter[0]), float(jitter[1])),
                       frame_index=index if isinstance(index, int) else None,
                       sequence=header.get("sequence", "") if isinstance(header.get("sequence"), str) else "",
                       camera_cut=bool(header.get("camera_cut", 0)), source=name)
    frame.attributes = {key: value for key, value in header.items()
                        if key in ("frame_index", "sequence", "scale", "camera_cut")}
    return frame


def encode_image_exr(rgb: np.ndarray, attributes: dict | None = None, compression: str = "none") -> bytes:
    """One-part float32 R/G/B EXR of an (H, W, 3) image, as bytes; ``attributes`` go into the header."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.shape[0] == 0 or rgb.shape[1] == 0:
        raise ValueError(f"an RGB image must have shape (H, W, 3), got {rgb.shape}")
    channels = {name: np.ascontiguousarray(rgb[:, :, c], dtype=np.float32) for c, name in enumerate("RGB")}
    header = {"compression": _compression(compression), "type": OpenEXR.scanlineimage, **(attributes or {})}
    stream = io.BytesIO()
    OpenEXR.File(header, channels).write(stream)
    return stream.getvalue()


def decode_image_exr(data: bytes, source: str = "the server's output") -> np.ndarray:
    """The (H, W, 3) float32 R/G/B image of a one-part EXR; FrameFileError if it is not one."""
    if bytes(data[:4]) != EXR_MAGIC:
        raise FrameFileError(f"{source}: not an OpenEXR file (wrong magic number)")
    try:
        exr = OpenEXR.File(io.BytesIO(bytes(data)), separate_channels=True)
        channels = exr.parts[0].channels
    except Exception as error:
        raise FrameFileError(f"{source}: unreadable or truncated EXR ({error})") from None
    missing = [name for name in "RGB" if name not in channels]
    if missing:
        raise FrameFileError(f"{source}: not an RGB image: lacks channels {', '.join(missing)}")
    return np.stack([channels[name].pixels for name in "RGB"], axis=-1).astype(np.float32, copy=False)


def display_encode(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear radiance -> uint8 display values, ``clip(x, 0, 1) ** (1/2.2)`` (NaN as 0)."""
    linear = np.nan_to_num(np.asarray(rgb, dtype=np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return np.round(np.clip(linear, 0.0, 1.0) ** (1.0 / 2.2) * 255.0).astype(np.uint8)


def encode_png(rgb: np.ndarray) -> bytes:
    """An 8-bit RGB PNG of the display encoding of a linear (H, W, 3) image."""
    pixels = display_encode(rgb)
    if pixels.ndim != 3 or pixels.shape[2] != 3:
        raise ValueError(f"an RGB image must have shape (H, W, 3), got {pixels.shape}")
    height, width = pixels.shape[:2]
    rows = np.concatenate([np.zeros((height, 1), np.uint8), pixels.reshape(height, width * 3)], axis=1)  # filter 0

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6)) + chunk(b"IEND", b""))


# --- which files of a folder are frames --------------------------------------------------------------------


def manifest_format(path: str | os.PathLike) -> str | None:
    """The ``format`` of a manifest.json, or None where the file is missing, not JSON, or has none."""
    try:
        value = json.loads(Path(path).read_text()).get("format")
    except (OSError, ValueError, AttributeError):
        return None
    return value if isinstance(value, str) else None


def is_sequence_folder(folder: str | os.PathLike) -> bool:
    """A folder of this project's frame bundles: its manifest.json says ``denoiser-sequence/1``."""
    return manifest_format(Path(folder) / MANIFEST) == SEQUENCE_FORMAT


def sequence_frame_files(folder: str | os.PathLike) -> tuple[list[Path], bool]:
    """The frame files a sequence folder's manifest lists, in order, and whether its frames carry references."""
    folder = Path(folder)
    where = folder / MANIFEST
    try:
        manifest = json.loads(where.read_text())
        files = [folder / entry["file"] for entry in manifest["frames"]]
        scales = list(manifest.get("scales") or [])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise FrameFileError(f"{where}: not a readable sequence manifest ({type(error).__name__}: {error})") from None
    return files, bool(scales)


def renderer_frame_files(folder: str | os.PathLike) -> tuple[list[Path], list[str]]:
    """A renderer's sequence folder: its EXR files in name order, and the other files there, which are ignored
    (a renderer's or pipeline's manifest.json, previews, logs). FrameFileError where there is no EXR."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder} is not a folder")
    files, ignored = [], []
    for path in sorted(folder.iterdir()):
        if not path.is_file():
            continue
        if path.suffix.lower() == ".exr" and not path.name.startswith("."):
            files.append(path)
        else:
            ignored.append(path.name)
    if not files:
        raise FrameFileError(f"{folder} holds no .exr files" + (f" (only {', '.join(ignored)})" if ignored else ""))
    return files, ignored


def frame_file_name(index: int) -> str:
    return f"frame_{index:04d}.exr"
