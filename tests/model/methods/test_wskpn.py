"""WSKPN: presets and registry, shapes and finiteness, temporal accumulation and camera cuts, demodulation,
the re-parameterized inference form, gradients through unrolled steps, and a short overfit."""

import copy
import dataclasses

import pytest
import torch
from torch import nn

from model.methods.base import unbounded_step
from model.methods.registry import build_method, example_batch, flops_per_pixel, method_spec
from model.methods.wskpn import ACCUMULATION_ALPHA, INPUT_CHANNELS, PRESETS, WSKPN
from model.ops.demodulate import demodulation_divisor
from model.ops.output_bound import output_bound
from tests.builders import randomize_batch_norms, static_frame
from tests.model.methods.overfitting import overfit_l1


def test_registry_entry():
    spec = method_spec("wskpn")
    assert spec.learned and spec.scales == (1, 2)
    assert spec.presets == ("xs", "s", "m", "l") and spec.default_preset == "s"
    method = build_method("wskpn")
    assert isinstance(method, WSKPN) and method.preset == "s" and method.sizes == (3, 5, 7, 9, 11, 13)
    with pytest.raises(KeyError, match="no preset"):
        build_method("wskpn:xxl")


@pytest.mark.parametrize("preset, layers", [("s", 3), ("m", 6)])
def test_paper_presets_are_the_papers_plain_nets(preset, layers):
    # Figure 2: full-resolution stacks of 5x5 RepVGG blocks, 14 channels wide, last layer 6 importance + 6 fusion.
    method = build_method(f"wskpn:{preset}").reparameterize()
    convs = [m for m in method.modules() if isinstance(m, nn.Conv2d)]
    assert [c.out_channels for c in convs] == [14] * (layers - 1) + [12]
    assert convs[0].in_channels == INPUT_CHANNELS and all(c.kernel_size == (5, 5) for c in convs)
    expected = sum(c.in_channels * c.out_channels * 25 + c.out_channels for c in convs)
    assert method.parameter_count() == expected
    if preset == "s":
        assert expected == 11 * 14 * 25 + 14 + 14 * 14 * 25 + 14 + 14 * 12 * 25 + 12 == 12990


def test_presets_grow_in_parameters_and_flops():
    counts, flops = [], []
    for preset in PRESETS:
        method = build_method(f"wskpn:{preset}").eval()
        fused = copy.deepcopy(method).reparameterize()
        counts.append(fused.parameter_count())
        flops.append(flops_per_pixel(fused, 16, 16))
        # The fused form is cheaper: the branches' FLOPs collapse into one convolution per block.
        assert 0 < flops[-1] < flops_per_pixel(method, 16, 16)
    assert counts == sorted(counts) and flops == sorted(flops)


@pytest.mark.parametrize("preset", list(PRESETS))
def test_every_preset_gives_finite_output_with_and_without_history(preset):
    method = build_method(f"wskpn:{preset}")
    frame = example_batch(16, 16)
    with torch.no_grad():
        first, state = method.step(frame, None)
        second, state = method.step(frame, state)
    for output in (first, second):
        assert output.shape == (1, 3, 16, 16)
        assert torch.isfinite(output).all() and (output >= 0).all()
    assert set(state) == {"irradiance", "count", "depth", "normal", "jitter"}


def test_odd_sizes_and_batches_through_the_u_net():
    method = build_method("wskpn:l")
    frame = example_batch(13, 18, batch=2)
    with torch.no_grad():
        output, _ = method.step(frame, None)
    assert output.shape == (2, 3, 13, 18) and torch.isfinite(output).all()


def test_first_step_then_accumulation_then_camera_cut_resets_count():
    method = build_method("wskpn:xs")
    with torch.no_grad():
        _, state = method.step(static_frame(batch=2, seed=0), None)
        assert torch.equal(state["count"], torch.ones(2, 1, 16, 16))
        _, state = method.step(static_frame(batch=2, seed=1), state)
        assert torch.equal(state["count"], torch.full((2, 1, 16, 16), 2.0))
        _, state = method.step(static_frame(batch=2, seed=2, cut=[True, False]), state)
    assert torch.equal(state["count"][0], torch.ones(1, 16, 16))  # history dropped, restarts at 1 sample
    assert torch.equal(state["count"][1], torch.full((1, 16, 16), 3.0))
    # The restarted sample holds only its own frame's irradiance.
    frame = static_frame(batch=2, seed=2)
    torch.testing.assert_close(state["irradiance"][0], frame.color[0] / demodulation_divisor(frame.albedo)[0])


def test_accumulation_is_the_running_mean_and_a_failed_geometry_test_restarts():
    method = build_method("wskpn:xs")
    frames = [static_frame(seed=s) for s in range(3)]
    moved = frames[2].depth.clone()
    moved[..., :4, :] = 3.0  # the top rows now see a surface 50% farther away: disoccluded
    frames[2] = dataclasses.replace(frames[2], depth=moved)
    state = None
    with torch.no_grad():
        for frame in frames:
            _, state = method.step(frame, state)
    divisor = demodulation_divisor(frames[0].albedo)
    irradiance = [f.color / divisor for f in frames]
    expected = sum(irradiance) / 3  # counts 1, 2, 3 are below 1 / alpha, so the blend is the exact mean
    assert 3 < 1 / ACCUMULATION_ALPHA
    torch.testing.assert_close(state["irradiance"][..., 4:, :], expected[..., 4:, :])
    torch.testing.assert_close(state["irradiance"][..., :4, :], irradiance[2][..., :4, :])
    assert (state["count"][..., :4, :] == 1).all() and (state["count"][..., 4:, :] == 3).all()


def test_constant_irradiance_comes_back_exactly_remodulated():
    # Every weight-sharing kernel is normalized, so constant irradiance passes through whatever the network
    # predicts, and remodulation must restore each pixel's own color, with or without a diffuse albedo.
    frame = static_frame()
    albedo = torch.rand(1, 3, 16, 16) * 0.9 + 0.05
    albedo[..., :3, :] = 0.0  # no diffuse albedo (sky, metal): radiance is kept as is
    color = 0.7 * demodulation_divisor(albedo)
    frame = dataclasses.replace(frame, albedo=albedo, color=color)
    with torch.no_grad():
        output, _ = build_method("wskpn:s").step(frame, None)
    torch.testing.assert_close(output, color)
    torch.testing.assert_close(output[..., :3, :], torch.full((1, 3, 3, 16), 0.7))


def test_step_never_reads_the_reference():
    frame = dataclasses.replace(example_batch(16, 16), reference=torch.full((1, 3, 16, 16), float("nan")))
    with torch.no_grad():
        output, _ = build_method("wskpn:xs").step(frame, None)
    assert torch.isfinite(output).all()


@pytest.mark.parametrize("preset", ["xs", "s"])
def test_reparameterized_method_matches_training_form(preset):
    method = build_method(f"wskpn:{preset}")
    randomize_batch_norms(method, seed=4)
    method.eval()
    fused = copy.deepcopy(method).reparameterize()
    assert not any(isinstance(m, nn.BatchNorm2d) for m in fused.modules())
    frames = [example_batch(16, 16, seed=s) for s in (1, 2)]
    frames[1] = dataclasses.replace(frames[1], motion=torch.zeros_like(frames[1].motion), depth=frames[0].depth,
                                    normal=frames[0].normal)  # a second step that really uses history
    state = fused_state = None
    with torch.no_grad():
        for frame in frames:
            output, state = method.step(frame, state)
            fused_output, fused_state = fused.step(frame, fused_state)
            torch.testing.assert_close(fused_output, output, atol=1e-5, rtol=1e-4)


def test_gradients_reach_every_parameter_through_two_unrolled_steps():
    method = build_method("wskpn:xs").train()
    target = example_batch(16, 16, seed=9).color
    state = None
    loss = torch.zeros(())
    for seed in (1, 2):
        output, state = method.step(example_batch(16, 16, seed=seed), state)
        loss = loss + (output - target).abs().mean()
    loss.backward()
    for name, p in method.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_scale_two_is_denoise_then_bicubic_upscale():
    method = build_method("wskpn:xs", scale=2)
    base = build_method("wskpn:xs")
    base.load_state_dict(method.state_dict())
    frame = example_batch(16, 16, batch=2)
    with torch.no_grad():
        output, state = method.step(frame, None)
        low, _ = unbounded_step(base, frame, None)  # the x2 step bounds its upscaled output, not this
    assert output.shape == (2, 3, 32, 32) and torch.isfinite(output).all() and (output >= 0).all()
    assert state["irradiance"].shape == (2, 3, 16, 16)  # history stays at render resolution
    expected = torch.nn.functional.interpolate(low, scale_factor=2, mode="bicubic", align_corners=False)
    torch.testing.assert_close(output, torch.minimum(expected.clamp_min(0.0), output_bound(frame.color)))


def test_short_overfit_reduces_l1_loss():
    # One frame: a shading edge along a depth edge, multiplicative noise. The network can only learn where to put
    # filter weight, so a lower loss means the importance and fusion maps learned to respect the edge.
    frame = static_frame(seed=3)
    depth = frame.depth.clone()
    depth[..., 8:] = 3.0
    shade = torch.full((1, 1, 16, 16), 0.2)
    shade[..., 8:] = 1.0
    clean = frame.albedo * shade
    noisy = clean * torch.rand(1, 3, 16, 16, generator=torch.Generator().manual_seed(4)) * 2
    frame = dataclasses.replace(frame, color=noisy, depth=depth)
    method = build_method("wskpn:s").train()
    initial, final = overfit_l1(method, frame, clean, lr=1e-2)
    assert final <= 0.7 * initial, (initial, final)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_step_matches_cpu():
    method = build_method("wskpn:s").eval()
    frames = [static_frame(batch=2, seed=0), static_frame(batch=2, seed=1, cut=[True, False])]
    outputs = {}
    for device in ("cpu", "cuda"):
        moved = copy.deepcopy(method).to(device)
        state = None
        with torch.no_grad():
            for frame in frames:
                output, state = moved.step(frame.to(device), state)
        assert output.device.type == device
        outputs[device] = output.cpu()
    torch.testing.assert_close(outputs["cuda"], outputs["cpu"], atol=1e-4, rtol=1e-4)


def test_for_inference_is_the_fused_eval_form_with_the_same_output():
    method = WSKPN("s")
    frame = example_batch(16, 16)
    method.eval()
    with torch.no_grad():
        expected, _ = method.step(frame, None)
    fast = method.for_inference()
    assert not fast.training and all(block.is_reparameterized for block in fast.modules()
                                     if hasattr(block, "is_reparameterized"))
    with torch.no_grad():
        torch.testing.assert_close(fast.step(frame, None)[0], expected, atol=1e-5, rtol=1e-4)
