"""Reading other renderers' EXRs in a layout: every refusal a new user met is now accepted correctly or refused with
a message that names the fix."""

from __future__ import annotations

import dataclasses

import numpy as np
import OpenEXR
import pytest

from model.io.exr import FrameFormatError
from model.io.frames import FrameValidationError
from model.layouts import BUILTIN_LAYOUTS, load_layout, read_layout_frame, read_layout_frame_bytes
from tests.builders import synthetic_frame
from tests.model.layouts.exr_builders import bundle_channels, write_channels, write_parts

DENOISER, GENERIC = BUILTIN_LAYOUTS["denoiser"], BUILTIN_LAYOUTS["generic"]


def plain_frame(seed: int, index: int, width: int, height: int):
    """A valid frame without references (what a renderer writes for live input)."""
    frame = synthetic_frame(np.random.default_rng(seed), index, width, height, scales=(1,))
    return dataclasses.replace(frame, references={})


@pytest.fixture
def frame():
    return plain_frame(3, 5, 8, 6)


def header(frame, **extra) -> dict:
    return {"jitter": np.array(frame.jitter, np.float64), "frame_index": frame.frame_index, **extra}


def test_extra_aovs_are_ignored_and_reported(tmp_path, frame):
    channels = bundle_channels(frame)
    channels.update({"position.X": frame.depth, "position.Y": frame.depth, "position.Z": frame.depth,
                     "color.A": np.ones_like(frame.depth), "object_id": np.full(frame.depth.shape, 7, np.uint32)})
    read = read_layout_frame(write_channels(tmp_path / "f.exr", channels, header(frame)), DENOISER)
    assert read.ignored_channels == ("color.A", "object_id", "position.X", "position.Y", "position.Z")
    np.testing.assert_array_equal(read.frame.color, frame.color)
    assert read.frame.frame_index == 5 and read.frame_index_given and read.repairs == ()


def test_a_multi_part_file_with_an_aov_part_reads_and_reports_the_part(tmp_path, frame):
    aov = {"crypto.R": frame.depth, "crypto.G": frame.depth}
    path = write_parts(tmp_path / "f.exr", [("render", bundle_channels(frame), header(frame)), ("aovs", aov, {})])
    read = read_layout_frame(path, DENOISER)
    assert read.ignored_channels == ("crypto.G", "crypto.R")
    np.testing.assert_array_equal(read.frame.motion, frame.motion)


def test_arnold_style_rgba_n_z_reads_with_the_generic_layout(tmp_path, frame):
    channels = bundle_channels(frame, rename={"color": "", "normal": "N", "depth": ""})
    channels["A"] = np.ones_like(frame.depth)
    assert {"R", "G", "B", "A", "N.X", "Z"} <= set(channels)
    read = read_layout_frame(write_channels(tmp_path / "f.exr", channels, {"frame_index": 2}), GENERIC)
    np.testing.assert_array_equal(read.frame.color, frame.color)
    np.testing.assert_array_equal(read.frame.depth, frame.depth)
    np.testing.assert_array_equal(read.frame.normal, frame.normal)
    assert read.frame.jitter == (0.0, 0.0)  # no jitter attribute: samples at the pixel centres
    assert read.ignored_channels == ()  # the alpha is expected by the layout, not reported
    # The denoiser layout names what it looked for, what the file has and the fix.
    with pytest.raises(FrameFormatError, match=r"buffer 'color': required buffer is missing: layout 'denoiser' reads "
                                               r"it from color.R, color.G, color.B.*\(it has: A, B, G, N.X.*choose "
                                               r"the layout of the renderer"):
        read_layout_frame(tmp_path / "f.exr", DENOISER)


@pytest.mark.parametrize("fixture, albedo_pass", [("blender_orbit", "ViewLayer.Diffuse Color"),
                                                  ("blender_orbit_4_5", "ViewLayer.DiffCol")], ids=["5.0", "4.5"])
def test_a_blender_render_without_a_needed_pass_says_which_to_enable(tmp_path, fixture, albedo_pass):
    from tests.model.layouts.exr_builders import FIXTURES

    channels = {}
    for part in OpenEXR.File(str(FIXTURES / fixture / "frame_0001.exr"), separate_channels=True).parts:
        channels.update({name: channel.pixels for name, channel in part.channels.items()
                         if not name.startswith(albedo_pass)})
    path = write_channels(tmp_path / "f.exr", channels, {"Note": "fov_y_degrees=40"})
    # Both generations' names for the pass: what was looked for and what to enable.
    with pytest.raises(FrameFormatError, match=r"buffer 'albedo': required buffer is missing: layout 'blender-cycles' "
                                               r"reads it from ViewLayer.Diffuse Color.R, ViewLayer.Diffuse Color.G, "
                                               r"ViewLayer.Diffuse Color.B \| ViewLayer.DiffCol.R, .*enable the passes "
                                               r"Combined, Z, Normal, Vector and Diffuse Color.*Blender 5 names them "
                                               r".*Diffuse Color.*Blender 4.x .*DiffCol"):
        read_layout_frame(path, BUILTIN_LAYOUTS["blender-cycles"])


def test_a_blender_render_without_a_field_of_view_says_how_to_give_one_and_what_its_lens_stamp_gives(tmp_path):
    """A frame saved from Blender itself, not by scripts/render_blender.py: no note, and (with Output Properties >
    Metadata > Lens on) the focal length as Blender 4.5 writes it, "30.00". The fixture's camera: 30 mm, default
    36 mm sensor, 32x32."""
    import json

    from tests.model.layouts.exr_builders import BLENDER_ORBIT_4_5

    layout = BUILTIN_LAYOUTS["blender-cycles"]
    fixture = BLENDER_ORBIT_4_5 / "frame_0001.exr"
    channels = {name: channel.pixels for part in OpenEXR.File(str(fixture), separate_channels=True).parts
                for name, channel in part.channels.items()}
    fov_y = np.degrees(json.loads((BLENDER_ORBIT_4_5 / "cameras.json").read_text())[1]["fov_y"])
    bare = write_channels(tmp_path / "bare.exr", channels, {"Frame": "2"})
    with pytest.raises(FrameFormatError, match=r"needs the vertical field of view.*--fov-y DEGREES.*Output Properties "
                                               r"> Metadata > Note\)$"):
        read_layout_frame(bare, layout)
    lens = write_channels(tmp_path / "lens.exr", channels, {"Frame": "2", "Lens": "30.00"})
    with pytest.raises(FrameFormatError, match=rf"the header's Lens is 30 mm: .* that is --fov-y {fov_y:.4f} for "
                                               rf"this 32x32 image"):
        read_layout_frame(lens, layout)
    # Given that way, the depth is what the stamped note gives.
    np.testing.assert_allclose(read_layout_frame(lens, layout, fov_y_degrees=round(fov_y, 4)).frame.depth,
                               read_layout_frame(fixture, layout).frame.depth, rtol=1e-5)


def test_missing_jitter_is_zero_in_a_session_and_a_clear_error_for_stored_data(tmp_path, frame):
    path = write_channels(tmp_path / "f.exr", bundle_channels(frame), {"frame_index": 1})
    live = read_layout_frame(path, DENOISER, mode="live")
    assert live.frame.jitter == (0.0, 0.0)
    assert live.repairs == ("jitter: no 'jitter' attribute, read as 0 (samples at the pixel centres)",)
    with pytest.raises(FrameFormatError, match=r"missing header attribute 'jitter'.*layout whose sample.jitter is "
                                               r"\"centre\" or \"header-or-centre\" \(built-in: generic"):
        read_layout_frame(path, DENOISER, mode="strict")
    assert read_layout_frame(path, GENERIC).frame.jitter == (0.0, 0.0)


def blender_channels() -> dict[str, np.ndarray]:
    from tests.model.layouts.exr_builders import BLENDER_ORBIT

    channels = {}
    for part in OpenEXR.File(str(BLENDER_ORBIT / "frame_0001.exr"), separate_channels=True).parts:
        channels.update({name: channel.pixels for name, channel in part.channels.items()})
    return channels


@pytest.mark.parametrize("note, jitter", [("fov_y_degrees=40", (0.0, 0.0)),
                                          ("fov_y_degrees=40 jitter=0.25,-0.375", (0.25, -0.375)),
                                          ("jitter = -0.5 , 1e-1 fov_y_degrees=40", (-0.5, 0.1))])
def test_blenders_note_carries_the_jitter_or_leaves_the_sample_at_the_pixel_centre(tmp_path, note, jitter):
    path = write_channels(tmp_path / "f.exr", blender_channels(), {"Note": note})
    read = read_layout_frame(path, BUILTIN_LAYOUTS["blender-cycles"])
    assert read.frame.jitter == jitter and read.repairs == ()


@pytest.mark.parametrize("note, message", [
    ("fov_y_degrees=40 jitter=0.25,1e", r"attribute 'Note' has 'jitter=0.25,1e', not 'jitter=X,Y' with two numbers"),
    ("fov_y_degrees=40 jitter=0.75,0", r"attribute 'jitter': \(0.75, 0\) is outside \[-0.5, 0.5\]"),
])
def test_a_bad_jitter_in_blenders_note_is_refused_with_what_is_wrong(tmp_path, note, message):
    path = write_channels(tmp_path / "f.exr", blender_channels(), {"Note": note})
    with pytest.raises((FrameFormatError, FrameValidationError), match=message):
        read_layout_frame(path, BUILTIN_LAYOUTS["blender-cycles"])


def test_missing_frame_index_is_left_to_the_caller(tmp_path, frame):
    path = write_channels(tmp_path / "f.exr", bundle_channels(frame), {"jitter": np.zeros(2)})
    read = read_layout_frame(path, DENOISER)
    assert not read.frame_index_given and read.frame.frame_index == 0


@pytest.mark.parametrize("compression", [OpenEXR.DWAA_COMPRESSION, OpenEXR.B44_COMPRESSION])
def test_lossy_compressed_normals_are_renormalised_and_reported_but_refused_as_stored_data(tmp_path, compression):
    # Curved surfaces with a little bump (fully random normals would be mangled beyond any tolerance by B44).
    ys, xs = np.mgrid[0:32, 0:32] / 32.0
    bump = 0.1 * np.random.default_rng(0).normal(size=(32, 32, 3))
    normal = np.stack([np.sin(3 * xs), np.cos(2 * ys) * 0.5, np.ones_like(xs)], axis=-1) + bump
    normal = (normal / np.linalg.norm(normal, axis=-1, keepdims=True)).astype(np.float32)
    frame = plain_frame(0, 0, 32, 32)
    frame.normal = normal
    channels = bundle_channels(frame, rename={"normal": "N"})
    # As Arnold names them: the codecs are lossy on R, G, B channels only. In a part of their own (an AOV part).
    normals = {f"N.{rgb}": channels.pop(f"N.{xyz}") for xyz, rgb in zip("XYZ", "RGB")}
    path = write_parts(tmp_path / "f.exr", [("render", channels, header(frame)),
                                            ("normals", normals, {"compression": compression})], half=True)
    stored = read_layout_frame(path, GENERIC, mode="live")
    assert stored.repairs and stored.repairs[0].startswith("normal: ")
    assert "pixels renormalised" in stored.repairs[0]
    length = np.linalg.norm(stored.frame.normal, axis=-1)
    assert np.abs(length - 1).max() < 1e-2
    # Renormalising kept the direction the file gave.
    assert np.degrees(np.arccos(np.clip((stored.frame.normal * normal).sum(-1), -1, 1))).max() < 10
    assert read_layout_frame(path, GENERIC, mode="import").repairs == stored.repairs
    with pytest.raises(FrameValidationError, match=r"buffer 'normal': \d+ pixels are off unit length by up to .*store "
                                                   r"normals losslessly \(ZIP, PIZ\) or convert with denoiser import"):
        read_layout_frame(path, GENERIC, mode="strict")


def test_normals_far_from_unit_length_are_still_refused(tmp_path, frame):
    frame.normal = frame.normal * 1.5
    path = write_channels(tmp_path / "f.exr", bundle_channels(frame), header(frame))
    with pytest.raises(FrameValidationError, match="not unit length"):
        read_layout_frame(path, DENOISER, mode="live")


def test_layout_conventions_are_applied(tmp_path, frame):
    """Motion up / pointing to the current frame / NDC, planar depth and view-space normals."""
    layout_file = tmp_path / "renderer.toml"
    layout_file.write_text('''
name = "in-house"
[channels]
color = ["beauty.R", "beauty.G", "beauty.B"]
albedo = ["albedo.R", "albedo.G", "albedo.B"]
normal = ["Nv.X", "Nv.Y", "Nv.Z"]
depth = ["Zplanar.Z"]
motion = ["mv.X", "mv.Y"]
[motion]
points_to = "current"
units = "ndc"
y = "up"
[depth]
kind = "planar"
no_hit_at_or_above = 1e9
fov_y_attribute = "fovY"
[normal]
space = "view"
[sample]
jitter = "centre"
''')
    layout = load_layout(layout_file)
    height, width = frame.depth.shape
    fov_y = 60.0
    # A camera looking down -z in view space, rotated 90 degrees about world z: world = view @ R.
    rotation = np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1]], np.float64)
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation.T  # row vectors: v_camera = v_world @ R^T
    view_normal = (frame.normal.astype(np.float64) @ rotation.T).astype(np.float32)
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    tan_y = np.tan(np.radians(fov_y) / 2)
    ray_factor = np.sqrt(1 + ((xs - width / 2) / (width / 2) * tan_y * width / height) ** 2
                         + ((ys - height / 2) / (height / 2) * tan_y) ** 2)
    planar = (frame.depth / ray_factor).astype(np.float32)
    planar[0, 0] = 1e10  # nothing hit there
    ndc_to_current = -frame.motion / np.array([width / 2, -height / 2], np.float32)
    channels = {
        **{f"beauty.{c}": frame.color[..., i] for i, c in enumerate("RGB")},
        **{f"albedo.{c}": frame.albedo[..., i] for i, c in enumerate("RGB")},
        **{f"Nv.{c}": view_normal[..., i] for i, c in enumerate("XYZ")},
        "Zplanar.Z": planar, "mv.X": ndc_to_current[..., 0], "mv.Y": ndc_to_current[..., 1],
    }
    path = write_channels(tmp_path / "f.exr", channels,
                          {"fovY": fov_y, "worldToCamera": world_to_camera.astype(np.float32)})
    read = read_layout_frame(path, layout)
    np.testing.assert_allclose(read.frame.motion, frame.motion, atol=1e-5)
    expected_depth = frame.depth.copy()
    expected_depth[0, 0] = 0
    np.testing.assert_allclose(read.frame.depth, expected_depth, rtol=1e-5)
    expected_normal = frame.normal.copy()
    expected_normal[0, 0] = 0  # nothing hit: no normal
    np.testing.assert_allclose(read.frame.normal, expected_normal, atol=1e-5)
    # An option overrides the header's field of view; without one anywhere, the error names the fixes.
    wider = read_layout_frame(path, layout, fov_y_degrees=90.0).frame.depth
    assert wider[1, 1] > read.frame.depth[1, 1]
    bare = write_channels(tmp_path / "bare.exr", channels, {"worldToCamera": world_to_camera.astype(np.float32)})
    with pytest.raises(FrameFormatError, match=r"planar depth.*--fov-y DEGREES, or depth.fov_y_degrees"):
        read_layout_frame(bare, layout)
    no_matrix = write_channels(tmp_path / "nomatrix.exr", channels, {"fovY": fov_y})
    with pytest.raises(FrameFormatError, match=r"view-space normals, which need the camera's 4x4 'worldToCamera'"):
        read_layout_frame(no_matrix, layout)


def test_partial_buffers_and_non_float_channels_are_refused(tmp_path, frame):
    channels = bundle_channels(frame)
    del channels["albedo.G"]
    with pytest.raises(FrameFormatError, match=r"albedo.*partial buffer: has albedo.R, albedo.B but lacks albedo.G"):
        read_layout_frame(write_channels(tmp_path / "p.exr", channels, header(frame)), DENOISER)
    channels = bundle_channels(frame)
    channels["depth.Z"] = np.ones(frame.depth.shape, np.uint32)
    with pytest.raises(FrameFormatError, match=r"channel 'depth.Z' holds uint32"):
        read_layout_frame(write_channels(tmp_path / "u.exr", channels, header(frame)), DENOISER)


def test_bytes_and_files_read_the_same_and_references_parts_come_along(tmp_path, frame):
    from model.io.exr import write_frame

    with_references = synthetic_frame(np.random.default_rng(1), 2, 8, 6, scales=(1, 2))
    path = write_frame(tmp_path / "f.exr", with_references)
    from_bytes = read_layout_frame_bytes(path.read_bytes(), DENOISER, "body")
    from_file = read_layout_frame(path, DENOISER)
    assert from_bytes.frame.scales == from_file.frame.scales == (1, 2)
    np.testing.assert_array_equal(from_bytes.frame.reference(2), with_references.reference(2))
    np.testing.assert_array_equal(from_file.frame.color, with_references.color)


@pytest.mark.parametrize("name", ["blender-cycles", "generic"])
def test_the_pixel_limit_is_checked_from_the_headers_before_decoding_in_any_layout(monkeypatch, name):
    import model.io.exr
    from model.io.exr import FrameTooLarge
    from tests.model.layouts.exr_builders import blender_like_bomb

    decoded = []
    monkeypatch.setattr(model.io.exr, "_read_coalesced", lambda *args: decoded.append(args))
    bomb = blender_like_bomb(1024, 1024)
    assert len(bomb) < 100_000
    with pytest.raises(FrameTooLarge, match=r"bomb.exr: declares 1024x1024 = 1048576 pixels; the limit is 1000000"):
        read_layout_frame_bytes(bomb, BUILTIN_LAYOUTS[name], "bomb.exr", mode="live", max_pixels=1_000_000)
    assert decoded == []


def test_a_reference_render_may_declare_a_2x_render_of_the_limit(tmp_path):
    from model.io.exr import FrameTooLarge
    from model.layouts.read import read_layout_reference
    from tests.model.layouts.exr_builders import BLENDER_ORBIT, upscaled_copy

    blender = BUILTIN_LAYOUTS["blender-cycles"]
    frame = read_layout_frame(BLENDER_ORBIT / "frame_0000.exr", blender, max_pixels=1024)  # 32x32, 6 pass parts
    assert (frame.frame.width, frame.frame.height) == (32, 32)
    path = upscaled_copy(BLENDER_ORBIT / "references" / "frame_0000.exr", tmp_path / "ref.exr", 2)
    assert read_layout_reference(path, blender, max_pixels=1024)["reference"].shape == (64, 64, 3)
    with pytest.raises(FrameTooLarge, match="declares 64x64 = 4096 pixels; the limit is 4092 pixels per reference "
                                            "render"):
        read_layout_reference(path, blender, max_pixels=1023)


def test_a_required_buffer_missing_from_the_headers_is_refused_before_decoding(monkeypatch):
    import model.io.exr as exr
    from tests.builders import aov_bomb

    def decode(*args):
        raise AssertionError("decoded")

    monkeypatch.setattr(exr, "_read_coalesced", decode)
    reserved = []
    with pytest.raises(FrameFormatError, match="buffer 'color': required buffer is missing.*aov000.Y"):
        read_layout_frame_bytes(aov_bomb(8, 4, channels=3), BUILTIN_LAYOUTS["denoiser"], mode="live",
                                reserve=reserved.append)
    assert reserved == []  # refused before the memory budget was asked
