"""Writing EXR files as other renderers do (any channel names, parts, compression), for the layout tests."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import OpenEXR

from model.data.camera import Camera
from model.io.frames import BUFFERS, FrameBundle

FIXTURES = Path(__file__).parent / "data"
BLENDER_ORBIT = FIXTURES / "blender_orbit"  # 4 frames, 32x32, rendered by scripts/render_blender.py --seed 0
BLENDER_ORBIT_JITTERED = FIXTURES / "blender_orbit_jittered"  # the same, --jitter halton
BLENDER_ORBIT_4_5 = FIXTURES / "blender_orbit_4_5"  # 3 frames of the same clip by Blender 4.5 LTS (DiffCol, ...)


def bundle_channels(frame: FrameBundle, rename: dict[str, str] | None = None) -> dict[str, np.ndarray]:
    """The frame's render-resolution buffers as channel planes named as the frame bundle names them, or as
    ``rename`` maps buffer names ("normal" -> "N" gives N.X, N.Y, N.Z)."""
    rename = rename or {}
    planes = {}
    for name, array in frame.render_buffers().items():
        spec = BUFFERS[name]
        prefix = rename.get(name, name)
        stack = array[..., None] if spec.is_scalar else array
        for index, component in enumerate(spec.components):
            planes[f"{prefix}.{component}" if prefix else component] = np.ascontiguousarray(stack[..., index])
    return planes


def write_parts(path: Path, parts: list[tuple[str, dict[str, np.ndarray], dict]],
                compression=OpenEXR.ZIP_COMPRESSION, half: bool = False) -> Path:
    """One EXR part per (name, channels, header attributes), every part of the first part's size."""
    first = next(iter(parts[0][1].values()))
    height, width = first.shape[:2]
    window = (np.array([0, 0], np.int32), np.array([width - 1, height - 1], np.int32))
    built = []
    for name, channels, attributes in parts:
        header = {"compression": compression, "type": OpenEXR.scanlineimage, "displayWindow": window, **attributes}
        planes = {key: np.ascontiguousarray(plane, dtype=plane.dtype if plane.dtype.kind in "ui" else
                                            (np.float16 if half else np.float32)) for key, plane in channels.items()}
        built.append(OpenEXR.Part(header, planes, name))
    OpenEXR.File(built).write(str(path))
    return path


def write_channels(path: Path, channels: dict[str, np.ndarray], attributes: dict | None = None,
                   compression=OpenEXR.ZIP_COMPRESSION, half: bool = False) -> Path:
    """A one-part EXR with these channels and header attributes."""
    return write_parts(path, [("render", channels, attributes or {})], compression, half)


def blender_like_bomb(width: int, height: int, pass_size: tuple[int, int] | None = None) -> bytes:
    """A zero-filled EXR with the parts and channels of the Blender fixture (one part per pass, half floats, ZIP):
    a few hundred kilobytes declaring ``width`` x ``height`` pixels in every part, or in every part but the first
    (``ViewLayer.Combined``) when ``pass_size`` gives that one's (width, height)."""
    import io

    source = OpenEXR.File(str(BLENDER_ORBIT / "frame_0000.exr"), header_only=True)
    window = (np.array([0, 0], np.int32), np.array([width - 1, height - 1], np.int32))  # the same for all parts
    built = []
    for index, part in enumerate(source.parts):
        part_width, part_height = pass_size if (pass_size and index == 0) else (width, height)
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "displayWindow": window}
        planes = {channel.name: np.zeros((part_height, part_width), np.float16) for channel in part.header["channels"]}
        built.append(OpenEXR.Part(header, planes, part.name()))
    stream = io.BytesIO()
    OpenEXR.File(built).write(stream)
    return stream.getvalue()


def upscaled_copy(source: Path, destination: Path, factor: int) -> Path:
    """Every part and channel of ``source`` repeated ``factor`` times along both axes (a render at ``factor``x)."""
    parts = []
    for part in OpenEXR.File(str(source), separate_channels=True).parts:
        channels = {name: np.repeat(np.repeat(channel.pixels, factor, axis=0), factor, axis=1)
                    for name, channel in part.channels.items()}
        parts.append((part.name(), channels, {}))
    return write_parts(destination, parts)


def hit_points(camera: dict, depth: np.ndarray, jitter=(0.0, 0.0)) -> np.ndarray:
    """World position of every pixel's hit along its ray through (x + 0.5 + jitter) at distance ``depth``."""
    matrix = np.array(camera["matrix_world"])
    height, width = depth.shape
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    xs, ys = xs + jitter[0], ys + jitter[1]
    # Blender's camera looks down its -z axis with y up; its matrix's columns are right, up, backward.
    direction = np.stack([(xs / width * 2 - 1) * np.tan(camera["fov_x"] / 2),
                          (1 - ys / height * 2) * np.tan(camera["fov_y"] / 2), -np.ones_like(xs)], axis=-1)
    direction = direction @ matrix[:3, :3].T
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    return matrix[:3, 3] + depth[..., None] * direction


def floor_hits(frame, camera: dict, depth: np.ndarray, jitter=(0.0, 0.0)) -> np.ndarray:
    """World z of the hit point of every pixel's ray through (x + 0.5 + jitter) at distance ``depth`` along it."""
    return hit_points(camera, depth, jitter)[..., 2]


def image_positions(camera: dict, points: np.ndarray) -> np.ndarray:
    """(x, y) in the frame bundle's image coordinates (unjittered) of world ``points`` (..., 3), by the generator's
    pinhole projection (``model.data.camera``) of the recorded Blender camera (columns: right, up, backward)."""
    matrix = np.array(camera["matrix_world"])
    origin = matrix[:3, 3]
    pinhole = Camera(tuple(origin), tuple(origin - matrix[:3, 2]), tuple(matrix[:3, 1]), math.degrees(camera["fov_x"]))
    positions, _ = pinhole.project(points.reshape(-1, 3), camera["width"], camera["height"])
    return positions.reshape(*points.shape[:-1], 2)
