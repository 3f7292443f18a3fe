"""EXR frame files: exact round trips, half precision, atomic writes, and errors that name the file."""

from __future__ import annotations

import io
import pickle

import numpy as np
import OpenEXR
import pytest

from model.io.exr import FrameFormatError, encode_frame_exr, read_frame, read_frame_bytes, write_frame
from model.io.frames import BUFFERS, TARGET_FIELDS, FrameBundle, FrameValidationError

from tests.builders import make_frame, zero_bomb

ARRAY_FIELDS = ("color", "albedo", "normal", "depth", "motion", "diffuse", "specular", "specular_albedo", "roughness")


def assert_same_frame(read: FrameBundle, written: FrameBundle, **tolerance) -> None:
    for name in ARRAY_FIELDS:
        expected, actual = getattr(written, name), getattr(read, name)
        if expected is None:
            assert actual is None, name
        else:
            assert actual.dtype == np.float32 and actual.shape == expected.shape, name
            np.testing.assert_allclose(actual, expected, err_msg=name, **tolerance)
    assert read.scales == written.scales
    for attribute in TARGET_FIELDS.values():
        expected, actual = getattr(written, attribute), getattr(read, attribute)
        assert sorted(actual) == sorted(expected), attribute
        for scale in expected:
            assert actual[scale].dtype == np.float32, attribute
            np.testing.assert_allclose(actual[scale], expected[scale], err_msg=f"{attribute} x{scale}", **tolerance)
    assert read.jitter == written.jitter
    assert (read.frame_index, read.sequence, read.camera_cut) == (
        written.frame_index, written.sequence, written.camera_cut
    )


def write_raw_exr(path, channels: dict[str, np.ndarray], header: dict | None = None) -> None:
    """A single-part file as another renderer might write it."""
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, **(header or {})}, dict(channels)).write(str(path))


def raw_channels(frame: FrameBundle, dtype=np.float32) -> dict[str, np.ndarray]:
    channels = {}
    for name, array in frame.render_buffers().items():
        planes = [array] if array.ndim == 2 else [array[..., c] for c in range(array.shape[2])]
        for channel, plane in zip(BUFFERS[name].channels, planes):
            channels[channel] = np.ascontiguousarray(plane, dtype=dtype)
    return channels


def test_float_round_trip_is_exact(tmp_path):
    frame = make_frame(seed=1)
    frame.jitter = (0.1, -0.3)  # not representable in float32: a V2f attribute would change it
    path = write_frame(tmp_path / "frame_0003.exr", frame)
    assert_same_frame(read_frame(path), frame, rtol=0, atol=0)


def test_layout_is_a_render_part_plus_one_part_per_larger_scale(tmp_path):
    path = write_frame(tmp_path / "f.exr", make_frame(scales=(1, 2, 4)))
    parts = OpenEXR.File(str(path), separate_channels=True).parts
    assert [part.name() for part in parts] == ["render", "reference_x2", "reference_x4"]
    assert {"reference.R", "color.G", "depth.Z", "motion.Y"} <= set(parts[0].channels)
    assert [part.header["scale"] for part in parts] == [4, 2, 4]
    assert set(parts[2].channels) == {"reference.R", "reference.G", "reference.B"}
    assert (parts[2].width(), parts[2].height()) == (24, 16)
    assert read_frame(path).scales == (1, 2, 4)


def test_albedo_references_round_trip_exactly_next_to_each_reference(tmp_path):
    frame = make_frame(seed=4, scales=(1, 2, 4), albedo_references=True)
    path = write_frame(tmp_path / "f.exr", frame)
    parts = OpenEXR.File(str(path), separate_channels=True).parts
    assert [part.name() for part in parts] == ["render", "reference_x2", "reference_x4"]
    assert {"reference_albedo.R", "reference_specular_albedo.B", "reference.G", "color.R"} <= set(parts[0].channels)
    target_channels = {f"{name}.{c}" for name in ("reference", "reference_albedo", "reference_specular_albedo")
                       for c in "RGB"}
    assert set(parts[1].channels) == set(parts[2].channels) == target_channels
    assert_same_frame(read_frame(path), frame, rtol=0, atol=0)


def test_albedo_references_round_trip_in_half_within_half_precision(tmp_path):
    frame = make_frame(seed=6, scales=(2,), albedo_references=True)
    path = write_frame(tmp_path / "f.exr", frame, half=True)
    parts = OpenEXR.File(str(path), separate_channels=True).parts
    assert "reference_albedo.R" not in parts[0].channels and "reference_albedo.R" in parts[1].channels
    assert all(ch.pixels.dtype == np.float16 for part in parts for ch in part.channels.values())
    read = read_frame(path)
    assert_same_frame(read, frame, rtol=1e-3, atol=1e-6)
    assert not np.array_equal(read.reference_albedo(2), frame.reference_albedo(2))  # really stored as half


def test_frames_without_albedo_references_read_with_none(tmp_path):
    read = read_frame(write_frame(tmp_path / "f.exr", make_frame(scales=(1, 2))))
    assert read.scales == (1, 2) and read.reference_albedos == {} and read.reference_specular_albedos == {}


def test_minimal_frame_round_trips(tmp_path):
    frame = make_frame(scales=(), split=False)
    frame.specular_albedo = frame.roughness = None
    frame.camera_cut = False
    assert_same_frame(read_frame(write_frame(tmp_path / "f.exr", frame)), frame, rtol=0, atol=0)


def test_scale_two_reference_without_scale_one(tmp_path):
    frame = make_frame(scales=(2,))
    assert_same_frame(read_frame(write_frame(tmp_path / "f.exr", frame)), frame, rtol=0, atol=0)


def test_half_round_trip_within_half_precision(tmp_path):
    frame = make_frame(seed=2)
    path = write_frame(tmp_path / "f.exr", frame, half=True)
    parts = OpenEXR.File(str(path), separate_channels=True).parts
    assert all(ch.pixels.dtype == np.float16 for part in parts for ch in part.channels.values())
    assert_same_frame(read_frame(path), frame, rtol=1e-3, atol=1e-6)


def test_half_refuses_values_beyond_the_half_range(tmp_path):
    frame = make_frame()
    frame.depth[1, 1] = 1e5
    with pytest.raises(FrameValidationError, match=r"buffer 'depth': 1 values exceed the largest half float"):
        write_frame(tmp_path / "f.exr", frame, half=True)
    assert list(tmp_path.iterdir()) == []


def test_failed_write_leaves_the_existing_file_untouched(tmp_path):
    path = write_frame(tmp_path / "frame_0000.exr", make_frame())
    before = path.read_bytes()
    broken = make_frame(seed=5)
    broken.color[0, 0, 0] = np.nan
    with pytest.raises(FrameValidationError, match=r"frame_0000.exr: buffer 'color'"):
        write_frame(path, broken)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["frame_0000.exr"]  # no temporary left behind


def test_unwritable_directory_is_an_os_error(tmp_path):
    with pytest.raises(OSError, match="cannot write EXR"):
        write_frame(tmp_path / "missing" / "f.exr", make_frame())


def test_single_part_file_from_another_renderer(tmp_path):
    frame = make_frame(scales=(1,), split=False)
    channels = raw_channels(frame, np.float16)
    for c, channel in enumerate(BUFFERS["reference"].channels):
        channels[channel] = frame.reference(1)[..., c].copy()  # float reference next to half buffers
    write_raw_exr(tmp_path / "other.exr", channels, {"jitter": (0.25, -0.125)})  # a tuple is stored as V2f
    read = read_frame(tmp_path / "other.exr")
    assert read.jitter == (0.25, -0.125)
    assert (read.frame_index, read.sequence, read.camera_cut, read.scales) == (0, "", False, (1,))
    assert read.reference_albedos == {} and read.reference_specular_albedos == {}
    np.testing.assert_array_equal(read.reference(1), frame.reference(1))
    np.testing.assert_allclose(read.color, frame.color, rtol=1e-3)


@pytest.mark.parametrize("compression", ["NO", "RLE", "ZIPS", "ZIP", "PIZ"])
def test_frame_bytes_round_trip_exactly_with_every_lossless_compression(compression):
    frame = make_frame(seed=2, scales=(1, 2))
    data = encode_frame_exr(frame, compression=getattr(OpenEXR, f"{compression}_COMPRESSION"))
    assert_same_frame(read_frame_bytes(data, "body"), frame, rtol=0, atol=0)


def test_a_buffer_with_float_and_half_channels_reads(tmp_path):
    # The bindings read R, G, B channels of one prefix as one array, but refuse to when their types differ.
    frame = make_frame()
    channels = raw_channels(frame)
    channels["color.G"] = channels["color.G"].astype(np.float16)
    write_raw_exr(tmp_path / "f.exr", channels, {"jitter": (0.0, 0.0)})
    read = read_frame(tmp_path / "f.exr")
    np.testing.assert_array_equal(read.color[..., 0], frame.color[..., 0])
    np.testing.assert_allclose(read.color[..., 1], frame.color[..., 1], rtol=1e-3)


def test_an_alpha_channel_next_to_a_buffer_is_unknown(tmp_path):
    channels = raw_channels(make_frame())
    channels["color.A"] = np.ones((4, 6), np.float32)
    write_raw_exr(tmp_path / "f.exr", channels, {"jitter": (0.0, 0.0)})
    with pytest.raises(FrameFormatError, match=r"f.exr: unknown channels in part '.*': color.A$"):
        read_frame(tmp_path / "f.exr")


def test_single_part_file_with_a_scale_one_reference_albedo(tmp_path):
    frame = make_frame(scales=(1,), albedo_references=True)
    channels = raw_channels(frame)
    for name in ("reference", "reference_albedo"):
        for c, channel in enumerate(BUFFERS[name].channels):
            channels[channel] = frame.target_buffers(1)[name][..., c].copy()
    write_raw_exr(tmp_path / "other.exr", channels, {"jitter": (0.0, 0.0)})
    read = read_frame(tmp_path / "other.exr")
    np.testing.assert_array_equal(read.reference_albedo(1), frame.reference_albedo(1))
    assert read.reference_specular_albedos == {}


def test_albedo_reference_without_a_reference_is_refused_on_read(tmp_path):
    frame = make_frame(scales=(1,), albedo_references=True)
    channels = raw_channels(frame)
    for c, channel in enumerate(BUFFERS["reference_albedo"].channels):
        channels[channel] = frame.reference_albedo(1)[..., c].copy()
    write_raw_exr(tmp_path / "f.exr", channels, {"jitter": (0.0, 0.0)})
    with pytest.raises(FrameValidationError, match=r"f.exr: buffer 'reference_albedo': at scale 1 has no radiance"):
        read_frame(tmp_path / "f.exr")


def test_missing_file_is_named(tmp_path):
    with pytest.raises(FrameFormatError, match=r"nope.exr: file not found"):
        read_frame(tmp_path / "nope.exr")


def test_non_exr_file_is_named(tmp_path):
    path = tmp_path / "notes.exr"
    path.write_text("not an image")
    with pytest.raises(FrameFormatError, match=r"notes.exr: not an OpenEXR file"):
        read_frame(path)


@pytest.mark.parametrize("scales", [(), (1, 2, 4)], ids=["single part", "three parts"])
def test_truncated_file_is_named(tmp_path, scales):
    path = write_frame(tmp_path / "cut.exr", make_frame(scales=scales))
    data = path.read_bytes()
    # Cuts in the header, in the offset table and in each part's pixel data: the bindings drop parts whose
    # pixels fail to decode instead of raising, which read_frame must still notice.
    for keep in np.linspace(0.02, 0.999, 24):
        path.write_bytes(data[: int(len(data) * keep)])
        with pytest.raises(FrameFormatError, match=r"cut.exr: unreadable or truncated EXR"):
            read_frame(path)


def test_unknown_channels_are_listed(tmp_path):
    channels = raw_channels(make_frame())
    channels["emission.R"] = channels["Y"] = np.zeros((4, 6), np.float32)
    write_raw_exr(tmp_path / "f.exr", channels, {"jitter": (0.0, 0.0)})
    with pytest.raises(FrameFormatError, match=r"f.exr: unknown channels in part '.*': Y, emission.R$"):
        read_frame(tmp_path / "f.exr")


def test_partial_buffer_is_named(tmp_path):
    channels = raw_channels(make_frame())
    del channels["color.B"]
    write_raw_exr(tmp_path / "f.exr", channels, {"jitter": (0.0, 0.0)})
    partial = r"buffer 'color': partial buffer: has color.R, color.G but lacks color.B"
    with pytest.raises(FrameFormatError, match=partial):
        read_frame(tmp_path / "f.exr")


def test_missing_required_buffer_is_named(tmp_path):
    channels = raw_channels(make_frame())
    del channels["motion.X"], channels["motion.Y"]
    write_raw_exr(tmp_path / "f.exr", channels, {"jitter": (0.0, 0.0)})
    with pytest.raises(FrameFormatError, match=r"buffer 'motion': required buffer is missing"):
        read_frame(tmp_path / "f.exr")


def test_missing_jitter_is_named(tmp_path):
    write_raw_exr(tmp_path / "f.exr", raw_channels(make_frame()))
    with pytest.raises(FrameFormatError, match=r"f.exr: attribute 'jitter': missing header attribute"):
        read_frame(tmp_path / "f.exr")


@pytest.mark.parametrize(
    "scale, problem",
    [(2, r"2 in part 'render' does not match 1"), (1.5, r"1.5 in part 'render' is not a positive integer")],
)
def test_bad_scale_attribute_is_named(tmp_path, scale, problem):
    write_raw_exr(tmp_path / "f.exr", raw_channels(make_frame()), {"jitter": (0.0, 0.0), "scale": scale})
    with pytest.raises(FrameFormatError, match=rf"attribute 'scale': {problem}"):
        read_frame(tmp_path / "f.exr")


def test_reference_part_scale_must_match_its_name(tmp_path):
    frame = make_frame()
    reference = {f"reference.{c}": frame.reference(2)[..., i].copy() for i, c in enumerate("RGB")}
    window = (np.array([0, 0], np.int32), np.array([5, 3], np.int32))
    render = OpenEXR.Part({"jitter": np.zeros(2), "scale": 3, "displayWindow": window}, raw_channels(frame), "render")
    extra = OpenEXR.Part({"scale": 3, "displayWindow": window}, reference, "reference_x2")
    OpenEXR.File([render, extra]).write(str(tmp_path / "f.exr"))
    with pytest.raises(FrameFormatError, match=r"'scale': 3 in part 'reference_x2' does not match 2"):
        read_frame(tmp_path / "f.exr")


def _two_part_file(path, frame: FrameBundle, extra_channels: dict[str, np.ndarray]) -> None:
    """A render part plus a reference_x2 part holding ``extra_channels`` (scale-2 planes)."""
    window = (np.array([0, 0], np.int32), np.array([5, 3], np.int32))
    render = OpenEXR.Part({"jitter": np.zeros(2), "scale": 2, "displayWindow": window}, raw_channels(frame), "render")
    extra = OpenEXR.Part({"scale": 2, "displayWindow": window}, extra_channels, "reference_x2")
    OpenEXR.File([render, extra]).write(str(path))


def test_reference_part_may_hold_only_target_buffers(tmp_path):
    frame = make_frame()
    channels = {f"reference.{c}": frame.reference(2)[..., i].copy() for i, c in enumerate("RGB")}
    channels["albedo.R"] = np.zeros((8, 12), np.float32)
    _two_part_file(tmp_path / "f.exr", frame, channels)
    allowed = r"reference.R/G/B, reference_albedo.R/G/B, reference_specular_albedo.R/G/B"
    with pytest.raises(FrameFormatError, match=rf"part 'reference_x2' may hold only {allowed}, not albedo.R$"):
        read_frame(tmp_path / "f.exr")


def test_reference_part_without_the_radiance_reference_is_refused(tmp_path):
    frame = make_frame(albedo_references=True)
    channels = {f"reference_albedo.{c}": frame.reference_albedo(2)[..., i].copy() for i, c in enumerate("RGB")}
    _two_part_file(tmp_path / "f.exr", frame, channels)
    with pytest.raises(FrameFormatError, match=r"'reference': part 'reference_x2' has no reference channels"):
        read_frame(tmp_path / "f.exr")


def test_invalid_contents_are_validated_on_read(tmp_path):
    channels = raw_channels(make_frame())
    channels["depth.Z"][2, 1] = -4.0
    write_raw_exr(tmp_path / "f.exr", channels, {"jitter": (0.0, 0.0)})
    with pytest.raises(FrameValidationError, match=r"f.exr: buffer 'depth': 1 pixels are negative"):
        read_frame(tmp_path / "f.exr")


# --- declared size, checked before decoding ----------------------------------------------------------------


def test_a_frame_declaring_more_pixels_than_the_limit_is_refused_before_decoding(monkeypatch):
    import model.io.exr as exr

    bomb = zero_bomb(1024, 1024)
    assert len(bomb) < 100_000
    decoded = []
    monkeypatch.setattr(exr, "_read_coalesced", lambda *args: decoded.append(args))
    with pytest.raises(exr.FrameTooLarge, match=r"declares 1024x1024 = 1048576 pixels; the limit is 1000000") as info:
        read_frame_bytes(bomb, "bomb.exr", max_pixels=1_000_000)
    assert (info.value.pixels, info.value.limit, info.value.source) == (1048576, 1_000_000, "bomb.exr")
    assert decoded == []


def test_the_pixel_limit_counts_the_render_part_and_leaves_room_for_a_2x_reference(tmp_path):
    import pickle

    import model.io.exr as exr

    frame = make_frame(0, 8, 6, scales=(1, 2))
    path = write_frame(tmp_path / "f.exr", frame)
    read_frame(path, max_pixels=48)  # 48 render pixels, a 2x reference of 192 beside them
    with pytest.raises(exr.FrameTooLarge, match="= 48 pixels; the limit is 47 pixels per frame"):
        read_frame(path, max_pixels=47)
    exr.check_frame_file_pixels(path, 48)
    error = exr.FrameTooLarge("f.exr", "declares too much", 10, 5)
    assert pickle.loads(pickle.dumps(error)).pixels == 10


def test_the_pixel_limit_holds_every_pass_part_and_bounds_the_values_of_all_parts():
    import io

    import model.io.exr as exr
    from tests.model.layouts.exr_builders import BLENDER_ORBIT, blender_like_bomb

    # Blender writes one part per pass: 6 parts of 32x32 are one 1024-pixel frame (18 values a pixel), not 6 of them.
    exr.check_frame_file_pixels(BLENDER_ORBIT / "frame_0000.exr", 1024)
    with pytest.raises(exr.FrameTooLarge, match="= 1024 pixels; the limit is 1023 pixels per frame"):
        exr.check_frame_file_pixels(BLENDER_ORBIT / "frame_0000.exr", 1023)
    # A pass part larger than the first part is held to the limit too.
    parts = OpenEXR.File(io.BytesIO(blender_like_bomb(64, 64, pass_size=(32, 32))), header_only=True).parts
    with pytest.raises(exr.FrameTooLarge, match="64x64 = 4096 pixels in part 'ViewLayer.Depth'; the limit is 1024"):
        exr.check_declared_pixels(parts, "f.exr", 1024)
    # One part of a few pixels but very many channels: bounded by its values (pixels x channels).
    stream = io.BytesIO()
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {f"aov{i}.Y": np.zeros((10, 10), np.float16) for i in range(200)}).write(stream)
    parts = OpenEXR.File(io.BytesIO(stream.getvalue()), header_only=True).parts
    with pytest.raises(exr.FrameTooLarge, match=r"declares 20000 values \(pixels x channels\) in its 1 parts; the "
                                                r"limit is 12800 \(128 per pixel"):
        exr.check_declared_pixels(parts, "f.exr", 100)
    exr.check_declared_pixels(parts, "f.exr", 157)  # 128 x 157 = 20096 values


def test_the_decoded_size_is_refused_from_the_header_before_decoding(monkeypatch):
    import model.io.exr as exr
    from tests.builders import aov_bomb

    def decode(*args):
        raise AssertionError("decoded")

    monkeypatch.setattr(exr, "_read_coalesced", decode)
    bomb = aov_bomb(16, 8)
    with pytest.raises(exr.DecodeTooLarge) as refused:
        exr.read_frame_bytes(bomb, "bomb.exr", max_pixels=16 * 8, max_decoded_bytes=16 * 8 * 127 * 4 - 1)
    assert (refused.value.pixels, refused.value.limit) == (16 * 8 * 127 * 4, 16 * 8 * 127 * 4 - 1)
    assert "bomb.exr: decodes to 65024 bytes (pixels x channels x 4 bytes per value, all 1 parts)" in str(refused.value)
    assert pickle.loads(pickle.dumps(refused.value)).pixels == 65024
    parts = OpenEXR.File(io.BytesIO(bomb), header_only=True).parts
    assert exr.decoded_part_bytes(parts) == [("", 65024)] and exr.check_decoded_bytes(parts, "b", 65024) == 65024


def test_select_parts_keeps_the_chosen_parts_without_decoding_the_others():
    from model.io.exr import select_parts
    from tests.builders import with_reference_part

    frame = make_frame(scales=(1, 2))
    data = encode_frame_exr(frame)
    render_only = select_parts(data, [0])
    parts = OpenEXR.File(io.BytesIO(render_only), separate_channels=True).parts
    assert [part.name() for part in parts] == ["render"]
    assert np.array_equal(parts[0].channels["color.G"].pixels, frame.color[:, :, 1])
    # Parts after a dropped one are renumbered: the third part of three becomes the second of two.
    both = OpenEXR.File(io.BytesIO(select_parts(with_reference_part(data, 4), [0, 2])), separate_channels=True)
    assert [part.name() for part in both.parts] == ["render", "reference_x4"]
    assert both.parts[1].channels["reference.R"].pixels.shape == (frame.height * 4, frame.width * 4)
    # What it cannot read is left to the whole read: a one-part file, a truncated one.
    assert select_parts(zero_bomb(8, 8), [0]) is None
    assert select_parts(data[: len(data) // 2], [0]) is None
