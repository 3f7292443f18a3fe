"""A layout: how another renderer's EXR maps to a frame bundle (channel names and conventions).

A layout is a mapping (a TOML or JSON file, or one of ``model.layouts.builtin``) with these keys, every one but
``name`` and ``channels.color`` optional::

    name = "my-renderer"
    description = "what writes these files"
    hint = "how to make the renderer write what is missing"   # added to missing-buffer errors
    ignore = ["*.A", "crypto*"]            # channels known to be unused: ignored without being reported

    [channels]                             # frame-bundle buffer -> EXR channel names, in component order
    color = ["R", "G", "B"]
    normal = [["N.X", "N.Y", "N.Z"], ["N.R", "N.G", "N.B"]]   # alternatives: the first one present is used

    [motion]   points_to, units, y          # the vector's direction, pixels or ndc, y down or up
    [depth]    kind, no_hit_at_or_above, fov_y_degrees / fov_y_attribute
    [normal]   space, view_matrix_attribute
    [sample]   jitter, jitter_attribute, frame_index_attribute

Every key, its values and an example file: docs/frame-format.md, "Layout files". Every problem with a layout is a
LayoutError naming the layout, the key and what is allowed.
"""

from __future__ import annotations

import fnmatch
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from model.io.frames import BUFFERS


class LayoutError(ValueError):
    """A layout that cannot be used: unknown name, unreadable file, or a key with a wrong value."""


@dataclass(frozen=True)
class MotionConvention:
    points_to: str = "previous"  # "previous" | "current"
    units: str = "pixels"  # "pixels" | "ndc"
    y: str = "down"  # "down" | "up"


@dataclass(frozen=True)
class DepthConvention:
    kind: str = "ray"  # "ray" | "planar"
    no_hit_at_or_above: float | None = None
    fov_y_degrees: float | None = None
    fov_y_attribute: str | None = None


@dataclass(frozen=True)
class NormalConvention:
    space: str = "world"  # "world" | "view"
    view_matrix_attribute: str = "worldToCamera"


@dataclass(frozen=True)
class SampleConvention:
    jitter: str = "header"  # "header" | "centre" | "header-or-centre"
    jitter_attribute: str = "jitter"
    frame_index_attribute: str = "frame_index"


@dataclass(frozen=True)
class Layout:
    name: str
    # buffer -> alternatives, each a tuple of channel names in the buffer's component order
    channels: dict[str, tuple[tuple[str, ...], ...]]
    description: str = ""
    motion: MotionConvention = field(default_factory=MotionConvention)
    depth: DepthConvention = field(default_factory=DepthConvention)
    normal: NormalConvention = field(default_factory=NormalConvention)
    sample: SampleConvention = field(default_factory=SampleConvention)
    ignore: tuple[str, ...] = ()
    hint: str = ""  # how to make the renderer write a missing buffer, for error messages

    def is_ignored(self, channel: str) -> bool:
        return any(fnmatch.fnmatchcase(channel, pattern) for pattern in self.ignore)

    def channel_names(self, buffer: str) -> str:
        """The channels a buffer is read from, for messages: "R, G, B" or "N.X, N.Y, N.Z | N.R, N.G, N.B"."""
        return " | ".join(", ".join(names) for names in self.channels.get(buffer, ()))


_CHOICES = {
    ("motion", "points_to"): ("previous", "current"),
    ("motion", "units"): ("pixels", "ndc"),
    ("motion", "y"): ("down", "up"),
    ("depth", "kind"): ("ray", "planar"),
    ("normal", "space"): ("world", "view"),
    ("sample", "jitter"): ("header", "centre", "header-or-centre"),
}
_SECTIONS = {"motion": MotionConvention, "depth": DepthConvention, "normal": NormalConvention,
             "sample": SampleConvention}
_TOP_KEYS = {"name", "description", "hint", "channels", "ignore", *_SECTIONS}


def parse_layout(content: Any, origin: str) -> Layout:
    """A Layout from a parsed TOML/JSON mapping; ``origin`` (a file or a built-in name) goes into every error."""
    if not isinstance(content, dict):
        raise LayoutError(f"layout {origin}: expected a table of keys (name, channels, motion, depth, normal, "
                          f"sample, ignore), got {type(content).__name__}")
    unknown = sorted(set(content) - _TOP_KEYS)
    if unknown:
        raise LayoutError(f"layout {origin}: unknown key(s) {', '.join(unknown)}; allowed: "
                          f"{', '.join(sorted(_TOP_KEYS))}")
    name = content.get("name")
    if not isinstance(name, str) or not name:
        raise LayoutError(f"layout {origin}: 'name' must be a non-empty string")
    for key in ("description", "hint"):
        if not isinstance(content.get(key, ""), str):
            raise LayoutError(f"layout {origin}: '{key}' must be a string")
    ignore = content.get("ignore", [])
    if not isinstance(ignore, list) or not all(isinstance(pattern, str) for pattern in ignore):
        raise LayoutError(f"layout {origin}: 'ignore' must be a list of channel names or glob patterns")
    sections = {key: _section(content.get(key, {}), key, origin) for key in _SECTIONS}
    return Layout(name=name, description=content.get("description", ""), hint=content.get("hint", ""),
                  channels=_channels(content.get("channels"), origin), ignore=tuple(ignore), **sections)


def _channels(table: Any, origin: str) -> dict[str, tuple[tuple[str, ...], ...]]:
    if not isinstance(table, dict) or "color" not in table:
        raise LayoutError(f"layout {origin}: 'channels' must be a table with at least 'color' (buffer -> channel "
                          f"names), e.g. color = [\"R\", \"G\", \"B\"]")
    channels = {}
    for buffer, value in table.items():
        spec = BUFFERS.get(buffer)
        if spec is None:
            raise LayoutError(f"layout {origin}: channels.{buffer}: unknown buffer; buffers: {', '.join(BUFFERS)}")
        alternatives = value if value and all(isinstance(item, list) for item in value) else [value]
        for names in alternatives:
            if (not isinstance(names, list) or len(names) != len(spec.components)
                    or not all(isinstance(name, str) and name for name in names)):
                raise LayoutError(
                    f"layout {origin}: channels.{buffer} must be a list of {len(spec.components)} channel names "
                    f"(components {', '.join(spec.components)}), or a list of such lists; got {value!r}")
        channels[buffer] = tuple(tuple(names) for names in alternatives)
    return channels


def _section(table: Any, section: str, origin: str):
    convention = _SECTIONS[section]
    if not isinstance(table, dict):
        raise LayoutError(f"layout {origin}: '{section}' must be a table")
    allowed = convention.__dataclass_fields__
    for key, value in table.items():
        if key not in allowed:
            raise LayoutError(f"layout {origin}: unknown key {section}.{key}; allowed: {', '.join(allowed)}")
        choices = _CHOICES.get((section, key))
        if choices is not None and value not in choices:
            raise LayoutError(f"layout {origin}: {section}.{key} is {value!r}; allowed: {', '.join(choices)}")
        if key in ("no_hit_at_or_above", "fov_y_degrees"):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise LayoutError(f"layout {origin}: {section}.{key} must be a positive number, got {value!r}")
            if key == "fov_y_degrees" and value >= 180:
                raise LayoutError(f"layout {origin}: {section}.{key} must be below 180 degrees, got {value!r}")
        elif choices is None and not (isinstance(value, str) and value):
            raise LayoutError(f"layout {origin}: {section}.{key} must be a non-empty string, got {value!r}")
    return convention(**table)


def load_layout(name_or_path: str | Path) -> Layout:
    """A built-in layout by name (``denoiser``, ``blender-cycles``, ``generic``) or a layout file (.toml, .json)."""
    from model.layouts.builtin import BUILTIN_LAYOUTS

    if isinstance(name_or_path, str) and name_or_path in BUILTIN_LAYOUTS:
        return BUILTIN_LAYOUTS[name_or_path]
    path = Path(name_or_path)
    if path.suffix.lower() not in (".toml", ".json"):
        raise LayoutError(f"unknown layout {str(name_or_path)!r}: give a built-in layout "
                          f"({', '.join(BUILTIN_LAYOUTS)}) or a layout file ending in .toml or .json")
    return parse_layout(read_layout_file(path), str(path))


def read_layout_file(path: str | Path) -> dict:
    """The mapping a layout file (.toml or .json) holds, unchecked (``parse_layout`` checks it)."""
    path = Path(path)
    if not path.is_file():
        raise LayoutError(f"layout file {path} not found")
    try:
        text = path.read_text()
        return tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, json.JSONDecodeError) as error:
        raise LayoutError(f"layout file {path}: cannot be read ({error})") from None


def layout_from_value(value: str | dict) -> Layout:
    """A layout given over the network: a built-in name, or the layout itself as a mapping (never a file path:
    files are the client's)."""
    from model.layouts.builtin import BUILTIN_LAYOUTS

    if isinstance(value, str):
        if value not in BUILTIN_LAYOUTS:
            raise LayoutError(f"unknown layout {value!r}: built-in layouts are {', '.join(BUILTIN_LAYOUTS)}; for "
                              f"another, send the layout itself (the keys of a layout file) as an object")
        return BUILTIN_LAYOUTS[value]
    return parse_layout(value, "given in the request")
