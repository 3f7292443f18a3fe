"""Mismatch warnings: imported data that looks wrong is reported, with the layout key to try; right data is not."""

from __future__ import annotations

import copy
import dataclasses
import json
import re

import numpy as np
import pytest

from model.layouts import BUILTIN_LAYOUTS, parse_layout, read_layout_frame, read_layout_reference
from model.layouts.builtin import BLENDER_CYCLES
from model.layouts.checks import SequenceChecks
from tests.model.layouts.exr_builders import BLENDER_ORBIT


def orbit_frames(layout=BUILTIN_LAYOUTS["blender-cycles"]):
    frames = []
    for path in sorted(BLENDER_ORBIT.glob("frame_*.exr")):
        frame = read_layout_frame(path, layout).frame
        reference = read_layout_reference(BLENDER_ORBIT / "references" / path.name, layout)["reference"]
        frames.append(dataclasses.replace(frame, references={1: reference}))
    return frames


def warnings_of(frames) -> list[str]:
    checks = SequenceChecks(hints="test")
    for frame in frames:
        checks.add(frame)
    return checks.warnings()


def with_motion(**motion):
    content = copy.deepcopy(BLENDER_CYCLES)
    content["motion"] = {**content["motion"], **motion}
    return parse_layout(content, "test")


def test_right_conventions_give_no_warning():
    assert warnings_of(orbit_frames()) == []


@pytest.mark.parametrize("motion, says", [
    ({"y": "down"}, r"but with y flipped \(motion.y\) it would be"),
    ({"points_to": "current"}, r"worse than not warping at all.*with the opposite sign \(motion.points_to\)"),
    ({"units": "ndc"}, r"worse than not warping at all.*pixels read as NDC undone \(motion.units = \"pixels\"\)"),
])
def test_wrong_motion_conventions_are_reported_with_the_key_to_change(motion, says):
    found = warnings_of(orbit_frames(with_motion(**motion)))
    assert len(found) == 1 and found[0].startswith("motion: ")
    assert re.search(says, found[0]), found[0]


def test_view_space_normals_are_reported():
    # The fixture's world-space normals in each frame's camera space (the camera turns 4 degrees a frame).
    cameras = json.loads((BLENDER_ORBIT / "cameras.json").read_text())
    view = []
    for frame, camera in zip(orbit_frames(), cameras):
        rotation = np.array(camera["matrix_world"])[:3, :3]  # camera -> world; row vectors: n_view = n_world @ R
        view.append(dataclasses.replace(frame, normal=(frame.normal @ rotation).astype(np.float32)))
    found = warnings_of(view)
    assert any(warning.startswith("normal: ") and 'normal.space = "view"' in warning for warning in found), found


def test_inverted_depth_is_reported():
    frames = orbit_frames()
    inverted = [dataclasses.replace(frame, depth=np.where(frame.depth > 0, 1 / frame.depth, 0).astype(np.float32))
                for frame in frames]
    found = warnings_of(inverted)
    assert any(warning.startswith("depth: in 4 of 4 frames the depth shrinks") for warning in found), found


def test_planar_depth_read_as_ray_distance_is_reported():
    content = copy.deepcopy(BLENDER_CYCLES)
    content["depth"] = {"kind": "ray", "no_hit_at_or_above": 1e9}  # Cycles' planar Depth pass taken as ray distance
    found = warnings_of(orbit_frames(parse_layout(content, "test")))
    assert any(warning.startswith("depth: on the largest flat surface 1/depth is an exact affine function")
               and 'depth.kind = "planar"' in warning for warning in found), found
