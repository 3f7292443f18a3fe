"""Blender Cycles' conventions, proved on real Cycles output (the committed fixture, Blender 5.0.1, rendered by
``scripts/render_blender.py --out tests/model/layouts/data/blender_orbit --frames 4 --size 32 --ref-spp 256``:
a camera orbiting 4 degrees a frame around boxes and a sphere on a checkered floor before a checkered wall), the
same clip by Blender 4.5.15 LTS (``... --out tests/model/layouts/data/blender_orbit_4_5 --frames 3``: one part, the
4.x pass names DiffCol and GlossCol), which passes the same checks, and the 5.0.1 clip with a TAA jitter per frame
(``... --out tests/model/layouts/data/blender_orbit_jittered --jitter halton``: a camera shift, stamped into the
metadata note).

As the generator's tests do: warping the previous reference by the imported motion reproduces this frame's
reference, far better than not warping and than every other convention; depth is checked on known geometry (the
floor plane z = 0 and the recorded cameras); normals of the floor are world-space (0, 0, 1) in every frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from model.data.camera import frame_jitter
from model.layouts import BUILTIN_LAYOUTS, read_layout_frame, read_layout_reference
from model.layouts.checks import reprojection_psnr
from tests.model.layouts.exr_builders import BLENDER_ORBIT, BLENDER_ORBIT_4_5, BLENDER_ORBIT_JITTERED, floor_hits, \
    hit_points, image_positions

LAYOUT = BUILTIN_LAYOUTS["blender-cycles"]
# Each Blender generation's render of the orbit clip, and the name its diffuse colour pass has there.
CLIPS = {"blender-5.0": (BLENDER_ORBIT, "Diffuse Color"), "blender-4.5": (BLENDER_ORBIT_4_5, "DiffCol")}


def raw(path, name: str) -> np.ndarray:
    """A channel as Blender wrote it (before any conversion)."""
    for part in OpenEXR.File(str(path), separate_channels=True).parts:
        if name in part.channels:
            return part.channels[name].pixels.astype(np.float64)
    raise KeyError(name)


@dataclass
class Clip:
    folder: Path
    diffuse_pass: str  # the diffuse colour pass's name in this Blender generation

    def __post_init__(self):
        self.paths = sorted(self.folder.glob("frame_*.exr"))
        self.cameras = json.loads((self.folder / "cameras.json").read_text())
        self.frames = [read_layout_frame(path, LAYOUT).frame for path in self.paths]

    def references(self, index: int) -> dict[str, np.ndarray]:
        return read_layout_reference(self.folder / "references" / self.paths[index].name, LAYOUT)


@pytest.fixture(scope="module", params=list(CLIPS))
def clip(request):
    return Clip(*CLIPS[request.param])


def test_the_raw_multilayer_files_read_as_frames_with_nothing_unexpected_left_over(clip):
    # The fixture is what its Blender generation writes: the albedo pass under that generation's name.
    raw(clip.paths[1], f"ViewLayer.{clip.diffuse_pass}.R")  # KeyError if not
    read = read_layout_frame(clip.paths[1], LAYOUT)
    assert read.ignored_channels == () and read.repairs == ()
    assert read.frame.resolution == (32, 32) and read.frame.jitter == (0.0, 0.0)
    assert read.frame.frame_index == 2  # Blender's 'Frame' attribute: frame 2 of its timeline
    assert read.frame.specular_albedo is not None
    # Both passes are the Diffuse/Glossy Color passes whatever their name: equal to the raw channels.
    np.testing.assert_array_equal(read.frame.albedo[..., 0], raw(clip.paths[1], f"ViewLayer.{clip.diffuse_pass}.R"))


def test_vector_xy_is_the_offset_to_the_previous_frame_in_pixels_with_y_up(clip):
    """Reprojecting the previous high-sample render by the imported motion: PSNR far above no reprojection, and
    above every other reading of Blender's Vector pass."""
    for index in range(1, len(clip.frames)):
        previous, current = clip.references(index - 1)["reference"], clip.references(index)["reference"]
        motion = clip.frames[index].motion
        warped = reprojection_psnr(previous, current, motion)
        unwarped = reprojection_psnr(previous, current, None)
        print(f"frame {index}: reprojected {warped:.2f} dB, not reprojected {unwarped:.2f} dB")
        # measured: 5.0.1 29.3 / 28.4 / 28.6 dB against 17.0 / 17.1 / 16.8 dB; 4.5.15 29.3 / 28.4 dB against 17.0 / 17.1 dB
        assert warped > unwarped + 7.0
        for wrong in ([1, -1], [-1, 1], [-1, -1], [0.5, 0.5], [2, 2]):  # y down, x flipped, sign, units
            assert warped > reprojection_psnr(previous, current, motion * np.float32(wrong)) + 2.0


def test_vector_zw_looks_at_the_next_frame_so_the_layout_ignores_it(clip):
    # Frame 1 of the timeline has no earlier camera (it holds still before frame 1): X/Y are 0 there, and on the last
    # frame Z/W are 0 (no later one), whereas both move in between.
    first, last = clip.paths[0], clip.paths[-1]
    assert np.abs(raw(first, "ViewLayer.Vector.X")).max() < 1e-4 and np.abs(raw(first, "ViewLayer.Vector.Z")).max() > 1
    assert np.abs(raw(last, "ViewLayer.Vector.Z")).max() < 1e-4 and np.abs(raw(last, "ViewLayer.Vector.X")).max() > 1


def test_depth_pass_is_planar_and_the_import_turns_it_into_distance_along_the_ray(clip):
    for index, (frame, camera) in enumerate(zip(clip.frames, clip.cameras)):
        floor = frame.normal[..., 2] > 0.999
        on_floor = floor & (np.abs(floor_hits(frame, camera, frame.depth)) < 1e-3)
        assert on_floor.sum() > 0.9 * floor.sum() > 200  # box tops face up too, a few pixels
        # The raw pass read as a ray distance misses the floor by a quarter of a unit or more...
        raw_depth = raw(clip.paths[index], "ViewLayer.Depth.Z")
        assert np.median(np.abs(floor_hits(frame, camera, raw_depth)[on_floor])) > 0.1
        # ... and the sample is at the pixel centre: a quarter-pixel offset misses the floor too.
        shifted = floor_hits(frame, camera, frame.depth, jitter=(0.25, 0.25))
        assert np.median(np.abs(shifted[on_floor])) > 10 * np.median(np.abs(floor_hits(frame, camera,
                                                                                            frame.depth)[on_floor]))
        assert np.abs(frame.depth - raw_depth).max() > 0.1  # the conversion did something


def test_normals_are_world_space(clip):
    # The floor's normal is (0, 0, 1) in every frame while the camera turns by 4 degrees a frame.
    for frame, camera in zip(clip.frames, clip.cameras):
        on_floor = np.abs(floor_hits(frame, camera, frame.depth)) < 1e-3
        np.testing.assert_allclose(frame.normal[on_floor], np.tile([0.0, 0.0, 1.0], (on_floor.sum(), 1)), atol=1e-3)


def test_diffuse_color_is_a_noise_free_guide_at_one_sample(clip):
    # Away from texture and object edges, the 1spp Diffuse Color equals the 256spp box-filtered one (measured median
    # difference 2e-6), while the 1spp colour is as noisy as one sample is (median 0.01).
    for index, frame in enumerate(clip.frames):
        references = clip.references(index)
        padded = np.pad(frame.albedo, ((1, 1), (1, 1), (0, 0)), mode="edge")
        windows = np.stack([padded[i:i + 32, j:j + 32] for i in range(3) for j in range(3)])
        smooth = (windows.max(axis=0) - windows.min(axis=0)).max(axis=-1) < 1e-2
        assert smooth.sum() > 100
        assert np.median(np.abs(frame.albedo - references["reference_albedo"]).max(-1)[smooth]) < 1e-4
        assert np.median(np.abs(frame.color - references["reference"]).max(-1)[smooth]) > 1e-3


def jittered_frames():
    paths = sorted(BLENDER_ORBIT_JITTERED.glob("frame_*.exr"))
    cameras = json.loads((BLENDER_ORBIT_JITTERED / "cameras.json").read_text())
    return [read_layout_frame(path, LAYOUT).frame for path in paths], cameras


def test_a_jittered_render_reads_its_jitter_from_the_note_and_its_samples_lie_there():
    frames, cameras = jittered_frames()
    for index, (frame, camera) in enumerate(zip(frames, cameras)):
        assert frame.jitter == pytest.approx(frame_jitter(index), abs=1e-6) == camera["jitter"]
        # Depth through the jittered positions lands on the floor plane z = 0; through the centres it does not.
        floor = frame.normal[..., 2] > 0.999
        at_jitter = np.abs(floor_hits(frame, camera, frame.depth, jitter=frame.jitter)[floor])
        at_centre = np.abs(floor_hits(frame, camera, frame.depth)[floor])
        assert floor.sum() > 200 and np.median(at_jitter) < 1e-4
        if frame.jitter != (0.0, 0.0):
            assert np.median(at_centre) > 100 * np.median(at_jitter)


@pytest.mark.parametrize("source", [*CLIPS, "blender-5.0-jittered"])
def test_the_imported_motion_is_the_offset_from_the_sample_to_the_previous_unjittered_projection(source):
    """The frame bundle's motion, from known geometry: this frame's sample position (centre + jitter) lifted to the
    world by its depth and projected by the previous camera without its jitter. Cycles leaves the camera shift out of
    its Vector pass, so a jittered render needs no correction; the other reading (the previous frame's own jittered
    projection) would be off by the change of jitter."""
    jittered = source.endswith("jittered")
    if jittered:
        clip, cameras = jittered_frames()
    else:
        rendered = Clip(*CLIPS[source])
        clip, cameras = rendered.frames, rendered.cameras
    height, width = clip[0].depth.shape
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    for index in range(1, len(clip)):
        frame = clip[index]
        hit = frame.depth > 0
        position = np.stack([xs + frame.jitter[0], ys + frame.jitter[1]], axis=-1)
        points = hit_points(cameras[index], frame.depth, frame.jitter)
        expected = image_positions(cameras[index - 1], points) - position
        assert np.percentile(np.abs(expected - frame.motion)[hit], 99) < 1e-3  # measured: 1e-5 px
        change = np.subtract(clip[index - 1].jitter, frame.jitter)
        if jittered:
            assert np.median(np.abs(expected - (frame.motion + change))[hit].max(-1)) > 0.2
