"""Writing EXR files as other renderers do (any channel names, parts, compression), for the layout tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

from model.frames import BUFFERS, FrameBundle

FIXTURES = Path(__file__).parent / "data"
BLENDER_ORBIT = FIXTURES / "blender_orbit"  # 4 frames, 32x32, rendered by scripts/render_blender.py --seed 0


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
