"""Layout files and the built-in layouts: parsing, and an error naming the key and the fix for each mistake."""

from __future__ import annotations

import json

import pytest

from model.layouts import BUILTIN_LAYOUTS, LayoutError, layout_from_value, load_layout, parse_layout
from model.layouts.builtin import BLENDER_CYCLES


def test_builtin_layouts_by_name():
    assert set(BUILTIN_LAYOUTS) == {"denoiser", "blender-cycles", "generic"}
    cycles = load_layout("blender-cycles")
    assert cycles.motion.y == "up" and cycles.depth.kind == "planar" and cycles.sample.jitter == "header-or-centre"
    assert cycles.is_ignored("ViewLayer.Vector.Z") and not cycles.is_ignored("ViewLayer.Vector.X")
    assert load_layout("denoiser").channels["normal"] == (("normal.X", "normal.Y", "normal.Z"),)


def test_toml_and_json_files_give_the_same_layout(tmp_path):
    toml = tmp_path / "mine.toml"
    toml.write_text('name = "mine"\nignore = ["*.A"]\n[channels]\ncolor = ["R", "G", "B"]\n'
                    'normal = [["N.X", "N.Y", "N.Z"], ["N.R", "N.G", "N.B"]]\n[motion]\ny = "up"\n'
                    '[depth]\nkind = "planar"\nfov_y_degrees = 40.0\n')
    as_json = tmp_path / "mine.json"
    as_json.write_text(json.dumps({"name": "mine", "ignore": ["*.A"],
                                   "channels": {"color": ["R", "G", "B"],
                                                "normal": [["N.X", "N.Y", "N.Z"], ["N.R", "N.G", "N.B"]]},
                                   "motion": {"y": "up"}, "depth": {"kind": "planar", "fov_y_degrees": 40.0}}))
    assert load_layout(toml) == load_layout(as_json)
    layout = load_layout(toml)
    assert layout.channels["normal"][1] == ("N.R", "N.G", "N.B")
    assert layout.motion.points_to == "previous" and layout.depth.fov_y_degrees == 40.0
    assert layout.is_ignored("color.A")


@pytest.mark.parametrize("change, message", [
    ({"channels": {"albedo": ["R", "G", "B"]}}, "'channels' must be a table with at least 'color'"),
    ({"channels": {"color": ["R", "G"]}}, r"channels.color must be a list of 3 channel names"),
    ({"channels": {"color": ["R", "G", "B"], "emission": ["E"]}}, "channels.emission: unknown buffer"),
    ({"motion": {"y": "sideways"}}, r"motion.y is 'sideways'; allowed: down, up"),
    ({"motion": {"sign": "+"}}, r"unknown key motion.sign; allowed: points_to, units, y"),
    ({"depth": {"fov_y_degrees": 200}}, "below 180 degrees"),
    ({"sample": {"jitter": "random"}}, "allowed: header, centre, header-or-centre"),
    ({"colour": {}}, r"unknown key\(s\) colour"),
    ({"name": ""}, "'name' must be a non-empty string"),
])
def test_mistakes_are_named(change, message):
    content = {"name": "x", "channels": {"color": ["R", "G", "B"]}, **change}
    with pytest.raises(LayoutError, match=message):
        parse_layout(content, "test.toml")


def test_unknown_names_and_unreadable_files(tmp_path):
    with pytest.raises(LayoutError, match=r"unknown layout 'arnold': give a built-in layout \(denoiser, "
                                          r"blender-cycles, generic\) or a layout file"):
        load_layout("arnold")
    with pytest.raises(LayoutError, match="not found"):
        load_layout(tmp_path / "missing.toml")
    broken = tmp_path / "broken.toml"
    broken.write_text("name = ")
    with pytest.raises(LayoutError, match="cannot be read"):
        load_layout(broken)


def test_layouts_over_the_network_are_names_or_objects_never_paths():
    assert layout_from_value("generic") is BUILTIN_LAYOUTS["generic"]
    assert layout_from_value(BLENDER_CYCLES) == BUILTIN_LAYOUTS["blender-cycles"]
    with pytest.raises(LayoutError, match="send the layout itself"):
        layout_from_value("/etc/layout.toml")
