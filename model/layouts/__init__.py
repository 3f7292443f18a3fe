"""Layouts: how another renderer's EXR files map to frame bundles (``model.io.frames``).

``layout.py`` the mapping and its file format, ``builtin.py`` the built-in layouts, ``convert.py`` the conventions'
conversions, ``read.py`` reading one frame in a layout, ``checks.py`` warnings when imported data looks wrong.
"""

from model.layouts.builtin import BUILTIN_LAYOUTS
from model.layouts.layout import (
    Layout,
    LayoutError,
    layout_from_value,
    load_layout,
    parse_layout,
    read_layout_file,
)
from model.layouts.read import (
    LayoutFrame,
    read_bundle_buffers,
    read_layout_frame,
    read_layout_frame_bytes,
    read_layout_reference,
)

__all__ = ["BUILTIN_LAYOUTS", "Layout", "LayoutError", "LayoutFrame", "layout_from_value", "load_layout",
           "parse_layout", "read_bundle_buffers", "read_layout_file", "read_layout_frame", "read_layout_frame_bytes",
           "read_layout_reference"]
