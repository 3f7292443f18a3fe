"""The generated data is right, not only present: motion, noise, the lobe split, references, determinism."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from tests.model.data.conftest import psnr, render_frames, requires_llvm

pytestmark = requires_llvm


def warp_previous(previous: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Bilinear backward warp written out here, independent of model.ops: reads previous at centre + motion."""
    height, width = motion.shape[:2]
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    grid = np.stack([(xs + motion[..., 0]) / width * 2 - 1, (ys + motion[..., 1]) / height * 2 - 1], axis=-1)
    image = previous if previous.ndim == 3 else previous[..., None]
    warped = F.grid_sample(torch.from_numpy(image).permute(2, 0, 1)[None].float(),
                           torch.from_numpy(grid[None]).float(), align_corners=False, padding_mode="border")
    return warped[0].permute(1, 2, 0).numpy()


def smooth_depth(depth: np.ndarray, tolerance: float = 0.05) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood spans less than `tolerance` relative depth (away from edges)."""
    height, width = depth.shape
    padded = np.pad(depth, 1, mode="edge")
    window = np.stack([padded[i:i + height, j:j + width] for i in range(3) for j in range(3)])
    return (window.max(axis=0) - window.min(axis=0)) < tolerance * depth


def trackable_pixels(previous, current) -> np.ndarray:
    """Moving surface pixels that were visible in the previous frame (not disoccluded), away from edges."""
    height, width = current.depth.shape
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    px, py = xs + current.motion[..., 0], ys + current.motion[..., 1]
    inside = (px > 1) & (px < width - 1) & (py > 1) & (py < height - 1)
    warped_depth = warp_previous(previous.depth, current.motion)[..., 0]
    was_smooth = warp_previous(smooth_depth(previous.depth).astype(np.float32), current.motion)[..., 0] > 0.99
    # A disoccluded pixel reads some other surface's depth in the previous frame.
    same_surface = np.abs(warped_depth - current.depth) < 0.15 * current.depth
    moving = np.linalg.norm(current.motion, axis=-1) > 1.0
    return inside & smooth_depth(current.depth) & was_smooth & same_surface & (current.depth > 0) & moving


@pytest.mark.parametrize("fixture_name", ["fast_camera_frames", "moving_object_frames"])
def test_warping_previous_reference_by_motion_reproduces_current_reference(fixture_name, request):
    previous, current = request.getfixturevalue(fixture_name)[-2:]
    valid = trackable_pixels(previous, current)
    assert valid.sum() >= 15, "too few trackable pixels for a meaningful check"
    reference, previous_reference = current.reference(1), previous.reference(1)
    scale = reference.mean(axis=-1) + 0.02
    warped_error = np.abs(warp_previous(previous_reference, current.motion) - reference).mean(-1) / scale
    unwarped_error = np.abs(previous_reference - reference).mean(-1) / scale
    # Warping must explain the change between frames: small residual, far below not warping at all.
    assert np.median(warped_error[valid]) < 0.05
    assert np.median(warped_error[valid]) < 0.5 * np.median(unwarped_error[valid])


def test_first_frame_motion_is_zero_so_projection_matches_the_sample_positions(fast_camera_frames):
    # Frame 0's "previous" camera is its own: the motion is the projection of each hit point minus its
    # jittered sample position, which is 0 only if projection and ray generation agree exactly.
    first = fast_camera_frames[0]
    assert np.abs(first.motion).max() < 1e-3
    assert np.abs(fast_camera_frames[1].motion).max() > 3.0


def test_static_camera_gives_zero_motion_except_on_moving_objects(moving_object_frames):
    frame = moving_object_frames[-1]
    moving = np.linalg.norm(frame.motion, axis=-1) > 1e-3
    assert 0.02 < moving.mean() < 0.5  # only the slider moves


def test_oidn_gains_over_6db_on_generated_noise_and_gaussian_filtered_noise_fails():
    import pyoidn

    from model.data.render import RenderSettings, SceneRenderer
    from model.data.scenes import build_scene

    renderer = SceneRenderer(build_scene("diffuse_room", 0, 1), RenderSettings(64, 64, ref_spp=512,
                                                                               ref_scales=(1,)), seed=0)
    frame = renderer.render_frame(0)
    reference = frame.reference(1)
    denoised = pyoidn.denoise(frame.color, frame.albedo, frame.normal, hdr=True, clean_aux=True, quality="high")
    gain = psnr(denoised, reference) - psnr(frame.color, reference)
    assert gain >= 6.0, f"OIDN gained only {gain:.1f} dB: the noise is not per-pixel independent"

    # The control shows the check can fail: Mitsuba's default Gaussian filter spreads each sample over
    # neighbouring pixels, and OIDN then leaves that correlated noise in.
    sensor = renderer._sensor(renderer.scene.cameras[0], 64, 64, 1)
    sensor["film"]["rfilter"] = {"type": "gaussian"}
    gaussian_scene = renderer.mi.load_dict(renderer._scene_dict(0, sensor))
    correlated = np.ascontiguousarray(np.asarray(renderer.mi.render(gaussian_scene, spp=1, seed=7))[..., :3])
    denoised = pyoidn.denoise(correlated, frame.albedo, frame.normal, hdr=True, clean_aux=True, quality="high")
    assert psnr(denoised, reference) - psnr(correlated, reference) < 6.0


@pytest.mark.parametrize("scene", ["glass", "metals"])
def test_diffuse_plus_specular_is_color_and_both_carry_light(scene):
    frame = render_frames(scene, 1, (40, 32), ref_spp=16, ref_scales=(1,))[0]
    np.testing.assert_allclose(frame.diffuse + frame.specular, frame.color, rtol=1e-6, atol=1e-7)
    assert frame.diffuse.mean() > 0.01 and frame.specular.mean() > 0.005


def test_specular_surfaces_have_specular_albedo_and_no_diffuse_albedo():
    frame = render_frames("metals", 1, (48, 40), ref_spp=16, ref_scales=(1,))[0]
    metal = frame.specular_albedo.mean(axis=-1) > 0.5
    assert metal.sum() > 20
    assert np.abs(frame.albedo[metal]).max() == 0.0
    diffuse_surface = frame.roughness == 1.0
    assert diffuse_surface.sum() > 20 and frame.albedo[diffuse_surface].min() > 0.0
    hit = frame.depth > 0
    np.testing.assert_allclose(np.linalg.norm(frame.normal[hit], axis=-1), 1.0, atol=1e-4)


def test_one_sample_estimate_is_unbiased_against_the_reference():
    frame = render_frames("glass", 1, (64, 64), ref_spp=512, ref_scales=(1,))[0]
    ratio = frame.color.mean() / frame.reference(1).mean()
    assert abs(ratio - 1.0) < 0.05


def test_references_rendered_with_different_seeds_agree():
    first = render_frames("diffuse_room", 1, (48, 40), ref_spp=256, ref_scales=(1,), render_seed=1)[0]
    second = render_frames("diffuse_room", 1, (48, 40), ref_spp=256, ref_scales=(1,), render_seed=2)[0]
    # The stated tolerance: at 256 spp two independent references are within 0.5% in mean and >= 38 dB apart.
    assert psnr(first.reference(1), second.reference(1)) >= 38.0
    assert abs(first.reference(1).mean() / second.reference(1).mean() - 1.0) < 0.005
    assert not np.array_equal(first.color, second.color)  # the noise really did change
    np.testing.assert_array_equal(first.albedo, second.albedo)  # the scene did not


def test_same_seed_renders_identical_frames():
    first = render_frames("textured_detail", 1, (32, 24), ref_spp=8)[0]
    second = render_frames("textured_detail", 1, (32, 24), ref_spp=8)[0]
    for name in ("color", "albedo", "normal", "depth", "motion"):
        np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
    np.testing.assert_array_equal(first.reference(2), second.reference(2))


def test_without_jitter_every_sample_is_at_the_pixel_centre_and_the_guides_follow():
    jittered = render_frames("fast_camera", 2, (32, 24), ref_spp=4, seed=3)
    centred = render_frames("fast_camera", 2, (32, 24), ref_spp=4, seed=3, jitter=False)
    assert [f.jitter for f in centred] == [(0.0, 0.0), (0.0, 0.0)]
    assert all(f.jitter != (0.0, 0.0) for f in jittered)
    # The sample positions moved, so the noise-free guides differ; the references (pixel averages) do not.
    assert not np.array_equal(jittered[1].depth, centred[1].depth)
    np.testing.assert_array_equal(jittered[1].reference(1), centred[1].reference(1))


def test_scale_one_reference_is_the_mean_of_the_scale_two_reference(fast_camera_frames):
    frame = fast_camera_frames[0]
    double = frame.reference(2)
    assert double.shape == (2 * frame.height, 2 * frame.width, 3)
    np.testing.assert_allclose(frame.reference(1), double.reshape(frame.height, 2, frame.width, 2, 3).mean((1, 3)),
                               rtol=1e-5, atol=1e-7)


def test_moving_light_changes_the_image_while_nothing_moves_on_screen():
    frames = render_frames("moving_light", 6, (32, 32), ref_spp=64, ref_scales=(1,), only=[2, 3])
    still = np.linalg.norm(frames[1].motion, axis=-1) < 1e-3
    assert still.mean() > 0.95  # only the light itself moves
    change = np.abs(frames[1].reference(1) - frames[0].reference(1))[still].mean()
    assert change > 0.05 * frames[1].reference(1).mean()


def test_camera_cut_is_flagged_on_the_first_frame_of_the_new_shot():
    frames = render_frames("camera_cut", 4, (24, 16), ref_spp=4, ref_scales=(1,))
    assert [f.camera_cut for f in frames] == [False, False, True, False]


def test_mis_weight_stays_finite_for_extreme_pdfs():
    # A light sampled at a grazing angle right next to it has pdf ~1e19: a^2 overflows float32 and the
    # textbook a^2 / (a^2 + b^2) gave NaN pixels in a generated sequence.
    import drjit as dr

    from model.data.mitsuba_backend import load_mitsuba
    from model.data.render import _mis_weight

    mi = load_mitsuba()
    weights = np.asarray(_mis_weight(dr, mi.Float([2.0e19, 1.0e-20, 0.0, 1.0, float("inf")]),
                                     mi.Float([1.0e-20, 2.0e19, 1.0, 1.0, 1.0])))
    np.testing.assert_allclose(weights, [1.0, 0.0, 0.0, 0.5, 1.0])


def test_a_frame_that_once_had_nan_pixels_is_finite():
    frame = render_frames("diffuse_room", 12, (128, 128), ref_spp=1, seed=1, ref_scales=(1,), only=[3])[0]
    assert np.isfinite(frame.color).all()


def uniform_interior(*images: np.ndarray) -> np.ndarray:
    """Pixels not on the image border whose 3x3 neighbourhood holds one value in every image (all channels)."""
    height, width = images[0].shape[:2]
    uniform = np.zeros((height, width), dtype=bool)
    uniform[1:-1, 1:-1] = True
    for image in images:
        image = image if image.ndim == 3 else image[..., None]
        centre = image[1:-1, 1:-1]
        for dy, dx in ((i, j) for i in range(3) for j in range(3)):
            uniform[1:-1, 1:-1] &= (image[dy:dy + height - 2, dx:dx + width - 2] == centre).all(axis=-1)
    return uniform


def test_scale_one_reference_albedos_are_the_mean_of_the_scale_two_ones(fast_camera_frames):
    frame = fast_camera_frames[0]
    for name in ("reference_albedo", "reference_specular_albedo"):
        double = getattr(frame, name)(2)
        assert double.shape == (2 * frame.height, 2 * frame.width, 3)
        np.testing.assert_allclose(getattr(frame, name)(1),
                                   double.reshape(frame.height, 2, frame.width, 2, 3).mean((1, 3)), rtol=1e-6)
    # Textured surfaces: the target pixels resolve detail that one 1x sample per pixel cannot.
    blocks = frame.reference_albedo(2).reshape(frame.height, 2, frame.width, 2, 3)
    assert np.abs(blocks - blocks.mean((1, 3), keepdims=True)).max() > 0.05
    # Both estimate the same image, so their means agree (a misplaced or mis-scaled estimate would not).
    assert abs(frame.reference_albedo(1).mean() / frame.albedo.mean() - 1.0) < 0.05


def test_reference_albedo_equals_the_guide_on_flat_untextured_diffuse_surfaces(monkeypatch):
    from model.data import render

    # Force several passes (3072 target pixels at 2x, 5 samples each per pass: 16 = 5 + 5 + 5 + 1).
    monkeypatch.setattr(render, "MAX_ALBEDO_LANES", 64 * 48 * 5)
    frame = render_frames("diffuse_room", 1, (32, 24), ref_spp=4)[0]
    flat = uniform_interior(frame.albedo, frame.specular_albedo, frame.roughness) & (frame.roughness == 1.0)
    flat &= (frame.depth > 0) & smooth_depth(frame.depth)
    assert flat.sum() > 100
    np.testing.assert_array_equal(frame.reference_albedo(1)[flat], frame.albedo[flat])
    np.testing.assert_array_equal(frame.reference_specular_albedo(1)[flat], frame.specular_albedo[flat])
    # Elsewhere (object edges) the reference albedo is a mix of surfaces, which the 1x guide is not.
    edges = ~uniform_interior(frame.albedo)
    assert np.abs(frame.reference_albedo(1) - frame.albedo).max(axis=-1)[edges].max() > 0.05


def test_metal_pixels_have_no_reference_albedo_and_a_reference_specular_albedo():
    frame = render_frames("metals", 1, (32, 24), ref_spp=4)[0]
    metal = uniform_interior(frame.albedo, frame.specular_albedo) & (frame.specular_albedo.mean(axis=-1) > 0.5)
    assert metal.sum() > 10
    for scale in (1, 2):
        pixels = np.repeat(np.repeat(metal, scale, axis=0), scale, axis=1)
        assert frame.reference_albedo(scale)[pixels].max() == 0.0
        assert frame.reference_specular_albedo(scale)[pixels].min() > 0.0
    np.testing.assert_array_equal(frame.reference_specular_albedo(1)[metal], frame.specular_albedo[metal])


_SCALAR_RENDER = """
import sys, numpy as np
from tests.model.data.conftest import render_frames
from model.data.render import RenderSettings, SceneRenderer
from model.data.scenes import build_scene
renderer = SceneRenderer(build_scene("metals", 0, 2), RenderSettings(20, 12, ref_spp=64, albedo_spp=2,
                         variant=sys.argv[1]), seed=0)
frame = renderer.render_frame(1)
np.savez(sys.argv[2], depth=frame.depth, normal=frame.normal, albedo=frame.albedo, motion=frame.motion,
         color=frame.color, reference=frame.reference(1), reference_albedo=frame.reference_albedo(2))
"""


def test_scalar_variant_renders_the_same_guides_and_converges_to_the_same_image(tmp_path):
    # scalar_rgb is the fallback without LLVM 19: the same path code, one ray at a time. Each variant runs in
    # its own process, as a user's would.
    import subprocess
    import sys

    results = {}
    for variant in ("llvm_ad_rgb", "scalar_rgb"):
        out = tmp_path / f"{variant}.npz"
        subprocess.run([sys.executable, "-c", _SCALAR_RENDER, variant, str(out)], check=True, timeout=300)
        results[variant] = np.load(out)
    vector, scalar = results["llvm_ad_rgb"], results["scalar_rgb"]
    for name in ("depth", "normal", "albedo", "motion"):
        np.testing.assert_allclose(scalar[name], vector[name], atol=2e-3, err_msg=name)
    assert np.isfinite(scalar["color"]).all() and not np.array_equal(scalar["color"], vector["color"])
    assert abs(scalar["reference"].mean() / vector["reference"].mean() - 1.0) < 0.03
    assert abs(scalar["color"].mean() / vector["reference"].mean() - 1.0) < 0.25
    np.testing.assert_allclose(scalar["reference_albedo"].mean(), vector["reference_albedo"].mean(), rtol=0.05)
