"""scripts/render_blender.py with real Cycles (runs only where the optional `bpy` is installed): its frames import
with no warning, and Cycles' Vector pass carries object motion too (a moving checkered cube under a still camera)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from model.importer import import_sequence
from model.layouts import BUILTIN_LAYOUTS, read_layout_frame, read_layout_reference
from model.layouts.checks import reprojection_psnr, warp_previous

pytestmark = pytest.mark.skipif(importlib.util.find_spec("bpy") is None,
                                reason="needs Blender as a Python module (pip install --no-deps bpy==5.0.1)")
SCRIPT = Path(__file__).parent.parent / "scripts" / "render_blender.py"
LAYOUT = BUILTIN_LAYOUTS["blender-cycles"]


def test_a_moving_object_render_imports_and_its_motion_reprojects(tmp_path):
    out = tmp_path / "moving"
    subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), "--scene", "moving_object", "--frames", "3",
                    "--size", "32", "--ref-spp", "64", "--seed", "1"], check=True, capture_output=True, timeout=300)
    assert sorted(path.name for path in out.glob("*.exr")) == [f"frame_000{i}.exr" for i in range(3)]
    report = import_sequence(out, LAYOUT, tmp_path / "data")
    assert report.frames == 3 and report.warnings == [] and report.scales == (1,)
    frame = read_layout_frame(out / "frame_0002.exr", LAYOUT).frame
    previous, current = (read_layout_reference(out / "references" / f"frame_000{i}.exr", LAYOUT)["reference"]
                         for i in (1, 2))
    moving = np.linalg.norm(frame.motion, axis=-1) > 0.5  # the camera stands still: only the cube moves
    assert moving.sum() > 20
    warped_psnr = reprojection_psnr(previous, current, frame.motion)
    assert warped_psnr > reprojection_psnr(previous, current, None)
    warped, _ = warp_previous(previous, frame.motion)
    warped_error = np.median(np.abs(warped - current).mean(-1)[moving])
    unwarped_error = np.median(np.abs(previous - current).mean(-1)[moving])
    assert warped_error < 0.5 * unwarped_error  # measured 0.023 against 0.079
