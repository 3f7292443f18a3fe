"""denoiser import: a renderer's folder of frames becomes a validated sequence our datasets accept, or nothing."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil

import numpy as np
import OpenEXR
import pytest

from model.io.dataset import Dataset, DatasetError
from model.io.frames import box_downsample
from model.io.importer import import_sequence
from model.layouts import BUILTIN_LAYOUTS, read_layout_frame
from model.layouts.builtin import BLENDER_CYCLES
from cli.main import main
from tests.builders import synthetic_frame
from tests.model.layouts.exr_builders import BLENDER_ORBIT, BLENDER_ORBIT_4_5, bundle_channels, write_channels

CYCLES, GENERIC = BUILTIN_LAYOUTS["blender-cycles"], BUILTIN_LAYOUTS["generic"]


def test_a_blender_cycles_folder_imports_as_a_dataset_sequence(tmp_path):
    report = import_sequence(BLENDER_ORBIT, CYCLES, tmp_path / "data", name="orbit", scene="orbit", split="validation")
    assert report.frames == 4 and report.scales == (1,) and report.warnings == [] and report.ignored_channels == []
    dataset = Dataset(tmp_path / "data")
    assert dataset.names("validation") == ["orbit"]
    sequence = dataset.sequence("orbit")
    assert len(sequence) == 4 and sequence.scene == "orbit"
    for index, frame in enumerate(sequence):
        source = read_layout_frame(BLENDER_ORBIT / f"frame_{index:04d}.exr", CYCLES).frame
        assert frame.frame_index == index and frame.sequence == "orbit"  # renumbered from Blender's 1..4
        np.testing.assert_array_equal(frame.motion, source.motion)
        assert frame.reference(1).shape == (32, 32, 3) and frame.reference_albedo(1).shape == (32, 32, 3)
    manifest = json.loads((tmp_path / "data" / "orbit" / "manifest.json").read_text())
    assert manifest["metadata"]["layout"] == "blender-cycles"
    assert manifest["metadata"]["references"].endswith("references")


def test_blender_4_5_frames_import_with_no_extra_flags_as_an_independent_conversion_reads_them(tmp_path, capsys):
    """Blender 4.x names the albedo passes DiffCol and GlossCol (5.x: Diffuse Color, Glossy Color) and writes one
    part: the built-in layout reads them as they are. Motion and depth are checked against a conversion written here
    from the raw passes and the recorded cameras: Vector.X/Y with y flipped, and the planar Depth.Z scaled to the
    length of each pixel-centre ray (from the cameras' horizontal and vertical fields of view)."""
    out = tmp_path / "data"
    assert main(["import", "--layout", "blender-cycles", str(BLENDER_ORBIT_4_5), "--out", str(out), "--name",
                 "o45"]) == 0
    printed = capsys.readouterr()
    assert "imported 3 frames" in printed.out and "warning" not in printed.err
    cameras = json.loads((BLENDER_ORBIT_4_5 / "cameras.json").read_text())
    for index, frame in enumerate(Dataset(out).sequence("o45")):
        raw = {name: channel.pixels.astype(np.float64) for part in
               OpenEXR.File(str(BLENDER_ORBIT_4_5 / f"frame_{index:04d}.exr"), separate_channels=True).parts
               for name, channel in part.channels.items()}
        np.testing.assert_array_equal(frame.motion, np.stack([raw["ViewLayer.Vector.X"], -raw["ViewLayer.Vector.Y"]],
                                                             axis=-1).astype(np.float32))
        camera = cameras[index]
        ys, xs = np.mgrid[0:32, 0:32] + 0.5
        ray = np.stack([(xs / 16 - 1) * np.tan(camera["fov_x"] / 2), (1 - ys / 16) * np.tan(camera["fov_y"] / 2),
                        -np.ones_like(xs)], axis=-1)  # per unit of distance along the view axis
        planar = raw["ViewLayer.Depth.Z"]
        assert planar.max() < 100  # the floor and the wall fill the view: every ray hits
        np.testing.assert_allclose(frame.depth, planar * np.linalg.norm(ray, axis=-1), rtol=1e-5)
        assert np.abs(frame.depth - planar).max() > 0.5  # the rays off the view axis are longer
        np.testing.assert_array_equal(frame.albedo[..., 0], raw["ViewLayer.DiffCol.R"].astype(np.float32))
        np.testing.assert_array_equal(frame.specular_albedo[..., 2], raw["ViewLayer.GlossCol.B"].astype(np.float32))


def _generic_folder(folder, count: int, reference_scale: int | None, extra_channel: bool = False):
    """Generic-layout frames (R G B, N, Z, ...) with references at ``reference_scale`` x in references/."""
    rng = np.random.default_rng(7)
    folder.mkdir(parents=True)
    expected = []
    for index in range(count):
        frame = synthetic_frame(rng, index, 8, 6, scales=(1, 2))
        frame = dataclasses.replace(frame, diffuse=None, specular=None)
        channels = bundle_channels(frame, rename={"color": "", "normal": "N", "depth": ""})
        if extra_channel:
            channels["objectid.R"] = frame.depth
        write_channels(folder / f"shot.{index + 101}.exr", channels)  # no frame index, no jitter attribute
        if reference_scale is not None:
            (folder / "references").mkdir(exist_ok=True)
            reference = frame.reference(reference_scale)
            write_channels(folder / "references" / f"shot.{index + 101}.exr",
                           {c: reference[..., i] for i, c in enumerate("RGB")})
        expected.append(frame)
    return expected


def test_references_at_twice_the_resolution_give_both_scales(tmp_path):
    expected = _generic_folder(tmp_path / "shot", 3, reference_scale=2, extra_channel=True)
    report = import_sequence(tmp_path / "shot", GENERIC, tmp_path / "data")
    assert report.scales == (1, 2) and report.ignored_channels == ["objectid.R"]
    sequence = Dataset(tmp_path / "data").sequence("shot")
    for frame, original in zip(sequence, expected):
        np.testing.assert_array_equal(frame.reference(2), original.reference(2))
        np.testing.assert_allclose(frame.reference(1), box_downsample(original.reference(2), 2), atol=1e-6)
        assert frame.jitter == (0.0, 0.0)


def test_problems_are_named_and_leave_nothing_behind(tmp_path):
    _generic_folder(tmp_path / "shot", 3, reference_scale=1)
    (tmp_path / "shot" / "references" / "shot.102.exr").unlink()
    with pytest.raises(DatasetError, match=r"lacks the references of 1 frame\(s\), first shot.102.exr"):
        import_sequence(tmp_path / "shot", GENERIC, tmp_path / "data")
    assert not (tmp_path / "data" / "shot").exists()
    # A broken frame half-way: the sequence is not written at all.
    shutil.rmtree(tmp_path / "shot" / "references")
    (tmp_path / "shot" / "shot.102.exr").write_bytes(b"not an exr")
    with pytest.raises(ValueError, match="shot.102.exr: not an OpenEXR file"):
        import_sequence(tmp_path / "shot", GENERIC, tmp_path / "data")
    assert not (tmp_path / "data" / "shot").exists()
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="holds no .exr files"):
        import_sequence(tmp_path / "empty", GENERIC, tmp_path / "data")


def test_the_command_imports_prints_and_refuses(tmp_path, capsys):
    out = tmp_path / "data"
    assert main(["import", "--layout", "blender-cycles", str(BLENDER_ORBIT), "--out", str(out), "--name", "o"]) == 0
    printed = capsys.readouterr().out
    assert "imported 4 frames" in printed and "references at scales: 1" in printed
    # Again: the sequence exists (exit 2 naming --overwrite); an unknown layout; the wrong layout names the fix.
    assert main(["import", "--layout", "blender-cycles", str(BLENDER_ORBIT), "--out", str(out), "--name", "o"]) == 2
    assert "pass overwrite" in capsys.readouterr().err
    assert main(["import", "--layout", "arnold", str(BLENDER_ORBIT), "--out", str(out)]) == 2
    assert "unknown layout 'arnold'" in capsys.readouterr().err
    assert main(["import", "--layout", "denoiser", str(BLENDER_ORBIT), "--out", str(out), "--name", "d"]) == 2
    assert "choose the layout of the renderer that wrote it" in capsys.readouterr().err
    # A layout file with the wrong y direction: imported, with a warning naming the key.
    layout = tmp_path / "wrong.json"
    content = copy.deepcopy(BLENDER_CYCLES)
    content["motion"]["y"] = "down"
    layout.write_text(json.dumps(content))
    assert main(["import", "--layout", str(layout), str(BLENDER_ORBIT), "--out", str(out), "--name", "w"]) == 0
    assert "warning: motion: " in capsys.readouterr().err


def test_a_renderers_own_manifest_and_other_files_are_ignored_and_named(tmp_path, capsys):
    source = tmp_path / "orbit"
    shutil.copytree(BLENDER_ORBIT, source)
    (source / "manifest.json").write_text(json.dumps({"renderer": "cycles", "frames": 4}))  # no 'format'
    report = import_sequence(source, BUILTIN_LAYOUTS["blender-cycles"], tmp_path / "data")
    assert report.frames == 4 and report.ignored_files == ["cameras.json", "manifest.json"]
    assert main(["import", "--layout", "blender-cycles", str(source), "--out", str(tmp_path / "cli")]) == 0
    assert "ignored 2 file(s) that are not frames: cameras.json, manifest.json" in capsys.readouterr().out
