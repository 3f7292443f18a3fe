"""FrameBundle conventions and validate_frame: every check fires, names its buffer and says what is wrong."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from model.io.frames import (
    BUFFERS,
    FrameError,
    FrameValidationError,
    box_downsample,
    validate_frame,
)
from tests.builders import make_frame


def test_valid_frame_passes_and_properties_describe_it():
    frame = validate_frame(make_frame(), "frame_0003.exr")
    assert (frame.height, frame.width, frame.resolution) == (4, 6, (6, 4))
    assert frame.scales == (1, 2)
    assert frame.reference(2).shape == (8, 12, 3)
    np.testing.assert_allclose(frame.reference(1), box_downsample(frame.reference(2), 2))
    assert list(frame.render_buffers()) == [
        "color", "albedo", "specular_albedo", "diffuse", "specular", "normal", "depth", "roughness", "motion"
    ]


def test_missing_reference_scale_is_a_clear_key_error():
    frame = make_frame(scales=(1,))
    with pytest.raises(KeyError, match=r"no reference at scale 2 \(scales present: 1\)"):
        frame.reference(2)
    with pytest.raises(KeyError, match=r"no reference_albedo at scale 1 \(scales present: none\)"):
        frame.reference_albedo(1)


def test_albedo_references_are_optional_target_buffers():
    assert {name for name, spec in BUFFERS.items() if spec.resolution == "target"} == {
        "reference", "reference_albedo", "reference_specular_albedo"
    }
    assert BUFFERS["reference_albedo"].channels == ("reference_albedo.R", "reference_albedo.G", "reference_albedo.B")
    frame = make_frame(scales=(1, 2), albedo_references=True)
    frame.reference_albedos[1] = frame.reference_albedos[1].astype(np.float64)
    frame = validate_frame(frame, "x")
    assert frame.reference_albedo(1).dtype == np.float32 and frame.reference_albedo(1).flags.c_contiguous
    assert frame.reference_albedo(2).shape == frame.reference_specular_albedo(2).shape == (8, 12, 3)
    np.testing.assert_array_equal(frame.reference_specular_albedo(1), frame.reference_specular_albedos[1])
    assert list(frame.target_buffers(1)) == ["reference", "reference_albedo", "reference_specular_albedo"]
    assert list(make_frame(scales=(1,)).target_buffers(1)) == ["reference"]
    assert make_frame().target_buffers(4) == {}


def test_albedo_references_may_exceed_one_by_rounding():
    frame = make_frame(albedo_references=True)
    frame.reference_albedos[2][3, 3, 0] = 1.0009
    frame.reference_specular_albedos[1][0, 0, 2] = -0.0009
    validate_frame(frame, "x")


def test_validation_converts_to_float32_contiguous_and_keeps_the_input():
    frame = make_frame()
    original_color = frame.color
    frame.color = np.asfortranarray(frame.color.astype(np.float64))
    frame.jitter = np.array([0.25, -0.5])
    frame.frame_index = np.int64(7)
    checked = validate_frame(frame, "x")
    assert checked.color.dtype == np.float32 and checked.color.flags.c_contiguous
    np.testing.assert_array_equal(checked.color, original_color)
    assert checked.jitter == (0.25, -0.5) and type(checked.jitter[0]) is float
    assert type(checked.frame_index) is int
    assert checked.albedo is frame.albedo  # already float32 and contiguous: no copy
    assert frame.color.dtype == np.float64  # the caller's frame is not modified


def test_optional_buffers_may_be_absent():
    frame = make_frame(split=False, scales=())
    frame.specular_albedo = frame.roughness = None
    assert validate_frame(frame, "x").render_buffers().keys() == {"color", "albedo", "normal", "depth", "motion"}


def test_negative_zero_radiance_is_fine():
    frame = make_frame(split=False)
    frame.color[1, 1] = -0.0
    validate_frame(frame, "x")


def test_albedo_may_exceed_one_by_rounding():
    frame = make_frame()
    frame.albedo[1, 1, 0] = 1.0009
    validate_frame(frame, "x")


def test_error_message_names_source_buffer_and_problem():
    frame = make_frame()
    frame.normal[1:3, 2:4] *= 1.2
    frame.normal[2, 3] *= 1.1
    with pytest.raises(FrameValidationError) as caught:
        validate_frame(frame, "frame_0003.exr")
    error = caught.value
    assert isinstance(error, FrameError) and isinstance(error, ValueError)
    assert (error.source, error.buffer) == ("frame_0003.exr", "normal")
    assert str(error) == (
        "frame_0003.exr: buffer 'normal': 4 pixels are not unit length (worst |n| = 1.32 at pixel (3, 2)); "
        "normals must be unit length where depth > 0"
    )
    # Picklable with its fields, so it survives being sent between worker processes.
    copy = pickle.loads(pickle.dumps(error))
    fields = ("source", "buffer", "problem")
    assert [getattr(copy, f) for f in fields] == [getattr(error, f) for f in fields] and str(copy) == str(error)


def _set(name, value):
    def change(frame):
        setattr(frame, name, value(frame) if callable(value) else value)
    return change


def _poke(name, index, value):
    def change(frame):
        getattr(frame, name)[index] = value
    return change


def _reference(scale, value):
    def change(frame):
        frame.references[scale] = value(frame) if callable(value) else value
    return change


def _drop_reference(scale):
    def change(frame):
        del frame.references[scale]
    return change


def _target(attribute, scale, value):
    def change(frame):
        getattr(frame, attribute)[scale] = value(frame) if callable(value) else value
    return change


def _poke_target(attribute, scale, index, value):
    def change(frame):
        getattr(frame, attribute)[scale][index] = value
    return change


# (id, change to a valid frame, buffer named, regex of the problem)
BREAKAGES = [
    ("missing color", _set("color", None), "color", r"required buffer is missing"),
    ("missing motion", _set("motion", None), "motion", r"required buffer is missing"),
    ("color is 2-D", _set("color", lambda f: f.color[..., 0]), "color", r"shape \(4, 6\) is not \(H, W, 3\)"),
    ("color has 4 channels", _set("color", lambda f: np.zeros((4, 6, 4))), "color", r"not \(H, W, 3\)"),
    ("motion has 3 channels", _set("motion", lambda f: np.zeros((4, 6, 3))), "motion", r"is not \(H, W, 2\)"),
    ("depth has a channel axis", _set("depth", lambda f: f.depth[..., None]), "depth", r"is not \(H, W\)"),
    ("albedo resolution", _set("albedo", lambda f: f.albedo[:3]), "albedo",
     r"resolution 6x3 does not match color's 6x4"),
    ("roughness resolution", _set("roughness", np.zeros((4, 5))), "roughness", r"resolution 5x4 .* 6x4"),
    ("reference size", _reference(2, np.zeros((8, 10, 3))), "reference",
     r"at scale 2 has resolution 10x8, expected 12x8"),
    ("reference at scale 1 upscaled", _reference(1, lambda f: f.references[2]), "reference",
     r"at scale 1 has resolution 12x8, expected 6x4"),
    ("fractional scale", _reference(1.5, np.zeros((6, 9, 3))), "reference", r"scale 1.5 is not a positive integer"),
    ("zero scale", _reference(0, np.zeros((0, 0, 3))), "reference", r"scale 0 is not a positive integer"),
    ("NaN color", _poke("color", (2, 5, 1), np.nan), "color", r"1 pixels are not finite .* first at pixel \(5, 2\)"),
    ("Inf depth", _poke("depth", (slice(1, 3), 0), np.inf), "depth", r"2 pixels are not finite .* \(0, 1\)"),
    ("NaN motion", _poke("motion", (3, 1, 0), np.nan), "motion", r"not finite .* \(1, 3\)"),
    ("NaN reference", lambda f: f.references[2].__setitem__((7, 11, 2), np.nan), "reference",
     r"not finite .* \(11, 7\)"),
    ("negative color", _poke("color", (1, 2, 0), -0.5), "color",
     r"1 pixels are negative \(lowest -0.5 at pixel \(2, 1\)\)"),
    ("negative diffuse", _poke("diffuse", (0, 1, 2), -1e-7), "diffuse", r"1 pixels are negative"),
    ("negative specular", _poke("specular", (3, 3), -2.0), "specular", r"1 pixels are negative .* \(3, 3\)"),
    ("negative reference", lambda f: f.references[1].__setitem__((0, 0, 0), -1.0), "reference", r"negative"),
    ("albedo above one", _poke("albedo", (2, 2, 1), 1.01), "albedo", r"1 pixels are outside \[0, 1\] \(worst 1.01"),
    ("albedo below zero", _poke("albedo", (2, 2, 1), -0.01), "albedo", r"outside \[0, 1\] \(worst -0.01"),
    ("specular_albedo above one", _poke("specular_albedo", (0, 0), 1.5), "specular_albedo", r"outside \[0, 1\]"),
    ("roughness above one", _poke("roughness", (1, 4), 1.2), "roughness", r"outside \[0, 1\] .* \(4, 1\)"),
    ("negative depth", _poke("depth", (2, 3), -1.0), "depth", r"1 pixels are negative .* \(3, 2\)"),
    ("short normal", _poke("normal", (1, 1), [0.0, 0.5, 0.0]), "normal", r"1 pixels are not unit length .*0.5"),
    ("zero normal on a hit", _poke("normal", (1, 1), 0.0), "normal", r"not unit length \(worst \|n\| = 0 at"),
    ("jitter too large", _set("jitter", (0.6, 0.0)), "jitter", r"\(0.6, 0\) is outside \[-0.5, 0.5\]"),
    ("jitter not finite", _set("jitter", (float("nan"), 0.0)), "jitter", r"not finite"),
    ("jitter of three", _set("jitter", (0.1, 0.2, 0.3)), "jitter", r"not a pair of numbers"),
    ("diffuse without specular", _set("specular", None), "specular", r"missing but diffuse is given"),
    ("specular without diffuse", _set("diffuse", None), "diffuse", r"missing but specular is given"),
    ("split does not sum", _poke("diffuse", (2, 4, 0), 0.0), "diffuse",
     r"diffuse \+ specular differs from color at 1 pixels .* \(4, 2\)"),
    ("negative frame_index", _set("frame_index", -1), "frame_index", r"-1 is negative"),
    ("fractional frame_index", _set("frame_index", 1.5), "frame_index", r"1.5 is not an integer"),
    ("sequence not a string", _set("sequence", 7), "sequence", r"7 is not a string"),
    ("camera_cut not a bool", _set("camera_cut", "yes"), "camera_cut", r"'yes' is not a bool"),
    ("non-numeric buffer", _set("albedo", "white"), "albedo", r"is not a numeric array"),
]


# The same for the albedo references (frames that have them at scales 1 and 2).
ALBEDO_REFERENCE_BREAKAGES = [
    ("reference_albedo size", _target("reference_albedos", 2, np.zeros((8, 10, 3))), "reference_albedo",
     r"at scale 2 has resolution 10x8, expected 12x8 \(WxH: 2 x the render resolution 6x4\)"),
    ("reference_specular_albedo at scale 1 upscaled",
     _target("reference_specular_albedos", 1, lambda f: f.reference_specular_albedos[2]),
     "reference_specular_albedo", r"at scale 1 has resolution 12x8, expected 6x4"),
    ("reference_albedo has 4 channels", _target("reference_albedos", 1, np.zeros((4, 6, 4))), "reference_albedo",
     r"shape \(4, 6, 4\) is not \(H, W, 3\)"),
    ("reference_albedo fractional scale", _target("reference_albedos", 1.5, np.zeros((6, 9, 3))),
     "reference_albedo", r"scale 1.5 is not a positive integer"),
    ("reference_albedo not numeric", _target("reference_albedos", 1, "grey"), "reference_albedo",
     r"is not a numeric array"),
    ("reference_albedos not a dict", _set("reference_albedos", [np.zeros((4, 6, 3))]), "reference_albedos",
     r"is not a dict of scale -> array"),
    ("NaN reference_albedo", _poke_target("reference_albedos", 2, (7, 11, 2), np.nan), "reference_albedo",
     r"1 pixels are not finite .* first at pixel \(11, 7\)"),
    ("Inf reference_specular_albedo", _poke_target("reference_specular_albedos", 1, (1, 2, 0), np.inf),
     "reference_specular_albedo", r"not finite .* \(2, 1\)"),
    ("reference_albedo above one", _poke_target("reference_albedos", 1, (2, 3, 1), 1.01), "reference_albedo",
     r"1 pixels are outside \[0, 1\] \(worst 1.01 at pixel \(3, 2\)\)"),
    ("reference_specular_albedo below zero", _poke_target("reference_specular_albedos", 2, (0, 5, 0), -0.01),
     "reference_specular_albedo", r"outside \[0, 1\] \(worst -0.01 at pixel \(5, 0\)\)"),
    ("reference_albedo without its reference", _drop_reference(2), "reference_albedo",
     r"at scale 2 has no radiance reference at that scale \(reference scales present: 1\)"),
    ("reference_specular_albedo without any reference",
     lambda f: (f.references.clear(), f.reference_albedos.clear()), "reference_specular_albedo",
     r"at scale 1 has no radiance reference at that scale \(reference scales present: none\)"),
]


@pytest.mark.parametrize("change, buffer, problem", [b[1:] for b in BREAKAGES], ids=[b[0] for b in BREAKAGES])
def test_every_broken_convention_is_reported(change, buffer, problem):
    frame = make_frame()
    change(frame)
    with pytest.raises(FrameValidationError) as caught:
        validate_frame(frame, "frame_0003.exr")
    assert caught.value.buffer == buffer
    assert caught.value.source == "frame_0003.exr"
    assert str(caught.value).startswith(f"frame_0003.exr: ")
    assert f"'{buffer}': " in str(caught.value)
    assert caught.match(problem)


@pytest.mark.parametrize("change, buffer, problem", [b[1:] for b in ALBEDO_REFERENCE_BREAKAGES],
                         ids=[b[0] for b in ALBEDO_REFERENCE_BREAKAGES])
def test_every_broken_albedo_reference_is_reported(change, buffer, problem):
    frame = make_frame(albedo_references=True)
    validate_frame(frame, "frame_0003.exr")  # valid before the change
    change(frame)
    with pytest.raises(FrameValidationError) as caught:
        validate_frame(frame, "frame_0003.exr")
    assert (caught.value.buffer, caught.value.source) == (buffer, "frame_0003.exr")
    kind = "buffer" if buffer in BUFFERS else "attribute"
    assert str(caught.value).startswith(f"frame_0003.exr: {kind} '{buffer}': ")
    assert caught.match(problem)


def test_error_names_attributes_as_attributes():
    frame = make_frame()
    frame.jitter = (0.0, 0.75)
    with pytest.raises(FrameValidationError, match=r"^f.exr: attribute 'jitter': "):
        validate_frame(frame, "f.exr")


def test_every_buffer_has_channels_named_buffer_dot_component():
    assert BUFFERS["depth"].channels == ("depth.Z",)
    assert BUFFERS["roughness"].channels == ("roughness.Y",)
    assert BUFFERS["motion"].channels == ("motion.X", "motion.Y")
    assert BUFFERS["normal"].channels == ("normal.X", "normal.Y", "normal.Z")
    required = {name for name, spec in BUFFERS.items() if spec.required}
    assert required == {"color", "albedo", "normal", "depth", "motion"}


def test_box_downsample_averages_blocks():
    image = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_array_equal(box_downsample(image, 2), [[2.5, 4.5], [10.5, 12.5]])
    with pytest.raises(ValueError, match="does not divide"):
        box_downsample(np.zeros((3, 4)), 2)


def test_sanitizable_input_lets_repairable_values_through_but_not_broken_conventions():
    frame = make_frame()
    frame.color[1, 2] = np.inf
    frame.diffuse[1, 2] = np.inf  # Inf - Inf in the lobe check: not compared
    frame.albedo[2, 2, 0] = 1.7
    frame.depth[3, 1] = np.nan
    frame.motion[0, 4, 1] = -np.inf
    frame.jitter = (float("nan"), 0.9)
    with pytest.raises(FrameValidationError, match="buffer 'color': 1 pixels are not finite"):
        validate_frame(frame, "live")
    checked = validate_frame(frame, "live", sanitizable=True)
    assert np.isinf(checked.color[1, 2]).all() and checked.jitter[1] == 0.9

    frame.normal[2, 3] *= 2.0  # not unit length: a convention, refused even for live input
    with pytest.raises(FrameValidationError, match="buffer 'normal': 1 pixels are not unit length"):
        validate_frame(frame, "live", sanitizable=True)
    frame.normal[2, 3] /= 2.0
    frame.specular[3, 4] += 1.0  # diffuse + specular != color on finite pixels
    with pytest.raises(FrameValidationError, match="diffuse \\+ specular differs from color at 1 pixels"):
        validate_frame(frame, "live", sanitizable=True)
