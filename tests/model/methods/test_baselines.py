"""Identity, temporal accumulation and the SVGF-style filter on tiny synthetic frames with known answers."""

from __future__ import annotations

import math

import pytest
import torch

from model.methods.base import FrameBatch
from model.methods.baselines import SVGF, TemporalAccumulation, bicubic_upscale
from model.methods.registry import build_method, example_batch, flops_per_pixel, method_spec
from tests.builders import mse, noisy_constant, plane_frame

HEIGHT, WIDTH = 16, 16
BASELINES = ("identity", "accumulation", "accumulation:fast", "svgf")


def devices() -> list:
    cuda = pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device"))
    return ["cpu", cuda]


def run(method, frames: list[FrameBatch]):
    state, outputs = None, []
    for frame in frames:
        output, state = method.step(frame, state)
        outputs.append(output)
    return outputs, state


# identity


def test_identity_returns_the_noisy_input():
    color = torch.rand(2, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(0))
    output, state = build_method("identity").step(plane_frame(color), None)
    assert torch.equal(output, color)
    assert state == {}


def test_identity_at_scale_2_is_the_bicubic_upscale_of_the_input():
    color = 4.0 * torch.rand(1, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(1))
    output, _ = build_method("identity", scale=2).step(plane_frame(color), None)
    expected = torch.nn.functional.interpolate(color, scale_factor=2, mode="bicubic", align_corners=False)
    assert float(expected.max()) > float(color.max())  # the kernel rings above the brightest input ...
    torch.testing.assert_close(output, expected.clamp(0.0, float(color.max())))  # ... which the output bound clips


def test_bicubic_upscale_clamps_the_overshoot_at_edges():
    step_edge = torch.zeros(1, 1, 8, 8)
    step_edge[..., 4:] = 1.0
    raw = torch.nn.functional.interpolate(step_edge, scale_factor=2, mode="bicubic", align_corners=False)
    assert raw.min() < 0  # the premise: bicubic alone undershoots next to the edge
    assert bicubic_upscale(step_edge, 2).min() == 0.0


# temporal accumulation


@pytest.mark.parametrize("device", devices())
def test_accumulation_error_falls_with_frames_on_a_static_scene(device):
    generator = torch.Generator().manual_seed(2)
    truth = torch.full((1, 3, HEIGHT, WIDTH), 0.5, device=device)
    noisy = [noisy_constant(truth, generator) for _ in range(8)]
    outputs, state = run(build_method("accumulation"), [plane_frame(c) for c in noisy])
    errors = [mse(o, truth) for o in outputs]
    noisy_error = sum(mse(c, truth) for c in noisy) / len(noisy)
    # 8 frames of exact running mean (1 / alpha_min = 10 > 8): the variance falls as 1/8.
    assert errors[-1] < noisy_error / 4
    assert errors[-1] < errors[3] < errors[0]
    torch.testing.assert_close(outputs[-1], torch.stack(noisy).mean(dim=0), rtol=1e-5, atol=1e-5)
    assert torch.all(state["count"] == 8)
    assert outputs[-1].device.type == device


def test_accumulation_presets_set_the_minimum_blend_weight():
    assert build_method("accumulation").alpha_min == 0.1
    assert build_method("accumulation:fast").alpha_min == 0.2
    assert method_spec("accumulation").presets == ("default", "fast", "rectified")
    with pytest.raises(KeyError):
        TemporalAccumulation("slow")


def test_accumulation_count_resets_on_camera_cut_per_sample():
    generator = torch.Generator().manual_seed(3)
    truth = torch.full((2, 3, HEIGHT, WIDTH), 0.5)
    frames = [plane_frame(noisy_constant(truth, generator)) for _ in range(3)]
    cut_color = noisy_constant(truth, generator)
    frames.append(plane_frame(cut_color, camera_cut=[False, True]))
    outputs, state = run(build_method("accumulation"), frames)
    assert torch.all(state["count"][0] == 4)
    assert torch.all(state["count"][1] == 1)
    torch.testing.assert_close(outputs[-1][1], cut_color[1])  # no history: the frame itself


def test_accumulation_count_resets_where_depth_jumps():
    generator = torch.Generator().manual_seed(4)
    truth = torch.full((1, 3, HEIGHT, WIDTH), 0.5)
    frames = [plane_frame(noisy_constant(truth, generator)) for _ in range(3)]
    depth = torch.ones(1, 1, HEIGHT, WIDTH)
    depth[..., 4:8, 4:8] = 2.0  # an object appears in front of (well, behind) the plane: disoccluded
    last_color = noisy_constant(truth, generator)
    frames.append(plane_frame(last_color, depth=depth))
    outputs, state = run(build_method("accumulation"), frames)
    jumped = depth[0, 0] == 2.0
    assert torch.all(state["count"][0, 0][jumped] == 1)
    assert torch.all(state["count"][0, 0][~jumped] == 4)
    torch.testing.assert_close(outputs[-1][..., 4:8, 4:8], last_color[..., 4:8, 4:8])


@pytest.mark.parametrize("motion, jitter", [((1.0, 0.0), (0.0, 0.0)), ((1.0, 0.0), (0.5, 0.0)),
                                            ((0.0, 1.0), (0.0, 0.0))])
def test_accumulation_one_pixel_motion_shifts_history_by_one_pixel(motion, jitter):
    # Frame 0 shows a pattern; frame 1 is black and says "my pixel p was at p + (dx, dy) before". The output is
    # then half the pattern read one pixel to the right / below. The history is per pixel centre, so this
    # frame's jitter must not move it (reading at centre + jitter + motion shifted it by the jitter each frame).
    pattern = torch.rand(1, 3, HEIGHT, WIDTH, generator=torch.Generator().manual_seed(5)) + 0.1
    black = torch.zeros_like(pattern)
    method = build_method("accumulation")
    _, state = method.step(plane_frame(pattern), None)
    output, state = method.step(plane_frame(black, motion=motion, jitter=jitter), state)
    if motion[1] == 0.0:
        # With jitter 0.5 the geometry test reads the previous samples 1.5 px away: the last two columns fail.
        keep = -2 if jitter[0] else -1
        torch.testing.assert_close(output[..., :, :keep], 0.5 * pattern[..., :, 1:keep + 1 or None])
        edge, edge_count = output[..., :, -1], state["count"][..., :, -1]  # read off the image: no history
    else:
        torch.testing.assert_close(output[..., :-1, :], 0.5 * pattern[..., 1:, :])
        edge, edge_count = output[..., -1, :], state["count"][..., -1, :]
    assert torch.all(edge == 0.0)
    assert torch.all(edge_count == 1)


def test_accumulation_demodulates_so_texture_is_taken_from_this_frame():
    # Constant illumination 1 under a texture that changes between frames: the accumulated output follows the
    # current albedo (up to the demodulation epsilon: within 0.04 at albedo 0.2), because only illumination is carried
    # in the history. Accumulating color instead would be off by about a third of the albedo range.
    generator = torch.Generator().manual_seed(6)
    method = build_method("accumulation")
    state = None
    for _ in range(3):
        albedo = 0.2 + 0.8 * torch.rand(1, 3, HEIGHT, WIDTH, generator=generator)
        frame = plane_frame(albedo.clone())
        frame.albedo = albedo
        output, state = method.step(frame, state)
    torch.testing.assert_close(output, albedo, atol=0.04, rtol=0)


# SVGF


@pytest.mark.parametrize("device", devices())
def test_svgf_reduces_noise_on_a_constant_albedo_plane(device):
    generator = torch.Generator().manual_seed(7)
    truth = torch.full((1, 3, HEIGHT, WIDTH), 0.5, device=device)
    noisy = [noisy_constant(truth, generator) for _ in range(4)]
    outputs, state = run(build_method("svgf"), [plane_frame(c) for c in noisy])
    for color, output in zip(noisy, outputs):
        assert mse(output, truth) < mse(color, truth) / 20
    assert torch.all(state["count"] == 4)
    assert outputs[-1].device.type == device


def test_svgf_keeps_the_two_sides_of_a_hard_depth_edge_apart():
    # Left half at depth 1 with radiance 0.2, right half at depth 3 with radiance 1.0, same normal, heavy
    # noise. With the depth edge the columns next to it keep their own side's value; the control without
    # it shows the noise is strong enough that luminance alone would let the sides bleed.
    truth = torch.full((1, 3, HEIGHT, WIDTH), 0.2)
    truth[..., WIDTH // 2:] = 1.0
    depth = torch.ones(1, 1, HEIGHT, WIDTH)
    depth[..., WIDTH // 2:] = 3.0
    color = noisy_constant(truth, torch.Generator().manual_seed(8))
    edge_columns = slice(WIDTH // 2 - 2, WIDTH // 2 + 2)

    with_edge, _ = build_method("svgf").step(plane_frame(color, depth=depth), None)
    torch.testing.assert_close(with_edge[..., edge_columns].mean(dim=(0, 1, 2)),
                               truth[..., edge_columns].mean(dim=(0, 1, 2)), atol=0.03, rtol=0)

    flat, _ = build_method("svgf").step(plane_frame(color), None)
    assert float(flat[..., WIDTH // 2 - 1].mean()) > 0.3


def test_svgf_feeds_back_the_first_atrous_level_and_keeps_moments():
    generator = torch.Generator().manual_seed(9)
    truth = torch.full((1, 3, HEIGHT, WIDTH), 0.5)
    color = noisy_constant(truth, generator)
    output, state = build_method("svgf").step(plane_frame(color), None)
    assert set(state) == {"history", "mean", "mean_sq", "count", "depth", "normal", "jitter"}
    history_error = mse(state["history"] * (0.5 + 1e-3), truth)
    # One a-trous level already removes much of the noise, the full five remove more.
    assert mse(output, truth) < history_error < mse(color, truth) / 2


def test_svgf_returns_a_noise_free_constant_image_unchanged():
    # A noise-free constant image must come back unchanged: the edge-stopped kernel is renormalized per pixel,
    # also at the image border where taps fall outside.
    color = torch.full((1, 3, HEIGHT, WIDTH), 0.7)
    output, _ = SVGF().step(plane_frame(color), None)
    torch.testing.assert_close(output, color)


# every baseline


@pytest.mark.parametrize("name", BASELINES)
@pytest.mark.parametrize("device", devices())
def test_scale_2_returns_twice_the_resolution(name, device):
    frame = example_batch(HEIGHT, WIDTH, batch=2, seed=10, device=device)
    method = build_method(name, scale=2)
    output, state = method.step(frame, None)
    output, _ = method.step(frame, state)
    assert output.shape == (2, 3, 2 * HEIGHT, 2 * WIDTH)
    assert output.device.type == device
    assert torch.isfinite(output).all() and output.min() >= 0


@pytest.mark.parametrize("name", BASELINES)
def test_batch_with_one_camera_cut_matches_running_each_sample_alone(name):
    frames = [example_batch(HEIGHT, WIDTH, batch=2, seed=seed) for seed in (11, 12, 13)]
    frames[2].camera_cut = torch.tensor([False, True])
    # Reference must not be read: NaNs there would show up in the output.
    frames[2].reference = torch.full((2, 3, HEIGHT, WIDTH), math.nan)
    outputs, _ = run(build_method(name), frames)
    assert torch.isfinite(outputs[-1]).all()

    def sample(frame: FrameBatch, index: int) -> FrameBatch:
        tensors = {key: value[index:index + 1] for key, value in frame.tensors().items()}
        return FrameBatch(**tensors)

    continuing, _ = run(build_method(name), [sample(f, 0) for f in frames])
    restarted, _ = build_method(name).step(sample(frames[2], 1), None)
    torch.testing.assert_close(outputs[-1][0:1], continuing[-1], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(outputs[-1][1:2], restarted, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name", BASELINES)
def test_flops_per_pixel_and_parameter_count(name):
    method = build_method(name)
    flops = flops_per_pixel(method, HEIGHT, WIDTH)
    assert math.isfinite(flops) and flops >= 0
    assert method.parameter_count() == 0
    assert method_spec(name.split(":")[0]).scales == (1, 2)


@pytest.mark.parametrize("name", ["accumulation", "svgf"])
def test_the_rectified_preset_clips_a_stale_bright_history(name):
    # A light that was here and is gone: the plain history keeps it for many frames, the rectified one drops it.
    bright = plane_frame(torch.full((1, 3, HEIGHT, WIDTH), 40.0))
    dark_color = noisy_constant(torch.full((1, 3, HEIGHT, WIDTH), 0.2), torch.Generator().manual_seed(5))
    dark_color[:, :, 0, 0] = 40.0  # the lamp, still in a corner: the output bound allows the ghost's brightness
    results = {}
    for preset in ("default", "rectified"):
        method = build_method(f"{name}:{preset}" if preset != "default" else name)
        _, state = method.step(bright, None)
        for _ in range(3):
            _, state = method.step(bright, state)
        output, _ = method.step(plane_frame(dark_color), state)
        results[preset] = float(output.mean())
    assert results["default"] > 2.0  # the ghost of the light
    assert results["rectified"] < 0.3 * results["default"]
    with pytest.raises(KeyError, match="presets"):
        build_method("svgf:slow")
