"""MUNet: shapes and finiteness per preset and scale, history and camera cuts, the closed forms of its building
blocks (sinusoidal encoding, partial convolution, unjitter, history reprojection, sample count, pyramid),
gradients through unrolled steps, the albedo loss, and a short overfit."""

import functools
import math

import pytest
import torch

from model.methods.munet import (
    GEOMETRY_CHANNELS,
    HISTORY_CHANNELS,
    MAX_COUNT,
    MUNET_PRESETS,
    MUNet,
    reproject_history,
    sample_offsets,
    unjitter,
    update_sample_count,
)
from model.methods.munet_blocks import (
    PartialConv2d,
    affinity_kernel_logits,
    partitioning_pyramid_filter,
    sinusoidal_encoding,
)
from model.methods.registry import build_method, example_batch, flops_per_pixel, method_spec
from model.ops.kernels import apply_pixel_kernels
from tests.builders import sample
from tests.builders import static_frame as _static_frame
from tests.model.methods.overfitting import overfit_l1

# A static scene, with specular albedo and roughness.
static_frame = functools.partial(_static_frame, material=True)

PAPER_PARAMETERS = 0.644e6


# ---------------------------------------------------------------------------------------------------------------
# The method


def test_registry_entry():
    spec = method_spec("munet")
    assert spec.learned and spec.scales == (1, 2)
    assert spec.presets == ("xs", "s", "m", "l") and spec.default_preset == "s"
    method = build_method("munet", scale=2)
    assert isinstance(method, MUNet) and method.preset == "s" and method.scale == 2
    assert MUNet().scale == 2  # joint denoising + 2x upscaling is the default use


@pytest.mark.parametrize("preset", list(MUNET_PRESETS))
def test_every_preset_at_scale_2_gives_finite_upscaled_output(preset):
    method = build_method(f"munet:{preset}", scale=2)
    with torch.no_grad():
        first, state = method.step(example_batch(16, 16), None)
        second, state = method.step(example_batch(16, 16, seed=1), state)
    for output in (first, second):
        assert output.shape == (1, 3, 32, 32)
        assert torch.isfinite(output).all() and (output >= 0).all()
    channels = {**HISTORY_CHANNELS, **GEOMETRY_CHANNELS}
    assert set(state) == set(channels)
    assert all(state[name].shape == (1, c, 32, 32) for name, c in channels.items())


@pytest.mark.parametrize("preset", ["xs", "m"])
def test_scale_1_denoises_at_render_resolution(preset):
    method = build_method(f"munet:{preset}", scale=1)
    with torch.no_grad():
        output, state = method.step(example_batch(16, 16, batch=2), None)
        output, state = method.step(example_batch(16, 16, batch=2, seed=1), state)
    assert output.shape == (2, 3, 16, 16) and torch.isfinite(output).all() and (output >= 0).all()
    assert state["output"].shape == (2, 3, 16, 16)


def test_odd_sizes_run_at_both_scales():
    for scale in (1, 2):
        method = build_method("munet:xs", scale=scale)
        with torch.no_grad():
            output, state = method.step(example_batch(15, 13), None)
            output, _ = method.step(example_batch(15, 13, seed=1), state)
        assert output.shape == (1, 3, 15 * scale, 13 * scale) and torch.isfinite(output).all()


def test_missing_optional_buffers_fall_back():
    frame = example_batch(16, 16)
    frame.specular_albedo = frame.roughness = frame.diffuse = frame.specular = None
    method = build_method("munet:xs", scale=2)
    with torch.no_grad():
        output, state = method.step(frame, None)
    assert torch.isfinite(output).all()
    # Specular albedo 0 everywhere: the upscaled one is a convex filter of zeros.
    assert torch.equal(state["specular_albedo_up"], torch.zeros_like(state["specular_albedo_up"]))


def test_first_step_starts_history_from_one_sample():
    method = build_method("munet:xs", scale=2)
    with torch.no_grad():
        output, state = method.step(static_frame(), None)
        _, later = method.step(static_frame(seed=1), state)
    assert torch.equal(state["count_radiance"], torch.ones_like(state["count_radiance"]))
    assert torch.equal(state["output"], output)
    # The second frame blends its history: counts grow past 1 but stay within 2 (alpha in (0, 1)).
    count = later["count_radiance"]
    assert (count > 1).all() and (count < 2).all()


def test_presets_straddle_the_paper_size_and_grow_in_cost():
    methods = [build_method(f"munet:{p}", scale=2) for p in MUNET_PRESETS]
    params = [m.parameter_count() for m in methods]
    flops = [flops_per_pixel(m, 16, 16) for m in methods]
    assert params == sorted(params) and flops == sorted(flops) and flops[0] > 0
    assert params[0] < 20_000 and params[1] < 60_000  # CPU-trainable sizes
    assert abs(params[2] - PAPER_PARAMETERS) < 0.05 * PAPER_PARAMETERS  # "m" is the paper's size
    assert params[3] > PAPER_PARAMETERS


def test_camera_cut_resets_only_that_sample():
    method = build_method("munet:xs", scale=2)
    first = static_frame(2, seed=0, jitter=(0.25, -0.125))
    second = static_frame(2, seed=1, cut=[True, False], jitter=(-0.375, 0.25))
    with torch.no_grad():
        _, state = method.step(first, None)
        output, state = method.step(second, state)
        fresh_0, fresh_state_0 = method.step(sample(second, 0), None)
        _, state_1 = method.step(sample(first, 1), None)
        continued_1, _ = method.step(sample(second, 1), state_1)
        fresh_1, _ = method.step(sample(second, 1), None)
    torch.testing.assert_close(output[0:1], fresh_0)
    torch.testing.assert_close(state["radiance"][0:1], fresh_state_0["radiance"])
    torch.testing.assert_close(output[1:2], continued_1)
    assert not torch.allclose(continued_1, fresh_1, atol=1e-4)  # history matters, so the check above has teeth
    assert torch.equal(state["count_radiance"][0], torch.ones_like(state["count_radiance"][0]))
    assert (state["count_radiance"][1] > 1).all()


@pytest.mark.parametrize("preset", list(MUNET_PRESETS))
def test_gradients_reach_every_parameter_through_two_steps(preset):
    method = build_method(f"munet:{preset}", scale=2)
    state = None
    loss = torch.zeros(())
    for seed in range(2):
        frame = example_batch(16, 16, seed=seed)  # varied guides: a flat scene can leave ReLUs dead everywhere
        frame.jitter = torch.tensor([[0.25 * seed, -0.125]])
        output, state = method.step(frame, state)
        loss = loss + output.mean()
    loss.backward()
    for name, parameter in method.named_parameters():
        assert parameter.grad is not None, name
        assert torch.isfinite(parameter.grad).all(), name
        assert parameter.grad.abs().sum() > 0, name


def test_auxiliary_loss_is_the_albedo_l1_when_references_exist():
    method = build_method("munet:xs", scale=2)
    frames = [static_frame(seed=s) for s in range(2)]
    states, state = [], None
    for frame in frames:
        _, state = method.step(frame, state)
        states.append(state)
    assert method.auxiliary_loss(frames, states) is None

    for frame in frames:
        frame.reference_albedo = torch.full((1, 3, 32, 32), 0.8)
        frame.reference_specular_albedo = torch.full((1, 3, 32, 32), 0.1)
    loss = method.auxiliary_loss(frames, states)
    expected = torch.stack([(s["albedo_up"] - 0.8).abs().mean() + (s["specular_albedo_up"] - 0.1).abs().mean()
                            for s in states]).mean()
    assert loss.dim() == 0 and torch.isfinite(loss) and loss > 0
    torch.testing.assert_close(loss, expected)
    loss.backward()
    assert method.heads.guide.weight.grad.abs().sum() > 0  # the albedo filters learn from it

    frames[0].reference_albedo = torch.zeros(1, 3, 16, 16)
    with pytest.raises(ValueError, match="reference_albedo"):
        method.auxiliary_loss(frames, states)


def test_overfits_one_pair():
    """60 Adam steps on one fixed noisy 16x16 frame and its clean 32x32 target cut the L1 error by >= 30%."""
    g = torch.Generator().manual_seed(0)
    ys, xs = torch.meshgrid(torch.linspace(0, 1, 32), torch.linspace(0, 1, 32), indexing="ij")
    clean = torch.stack([0.2 + 0.6 * xs, 0.3 + 0.4 * ys, 0.5 + 0.3 * xs * ys]).unsqueeze(0)
    noise = -torch.log(torch.rand(1, 3, 16, 16, generator=g).clamp_min(1e-6))  # Exp(1): mean 1, heavy tail
    frame = static_frame(seed=0)
    frame.color = torch.nn.functional.avg_pool2d(clean, 2) * noise
    method = build_method("munet:xs", scale=2)
    initial, final = overfit_l1(method, frame, clean, lr=3e-3)
    assert final <= 0.7 * initial, (initial, final)


# ---------------------------------------------------------------------------------------------------------------
# Pre-processing closed forms


def test_unjitter_places_each_sample_on_the_target_grid():
    # A smooth ramp sampled at the jittered positions: render pixel x holds a * (x + 0.5 + jitter_x).
    a, jitter = 2.0, torch.tensor([[0.25, 0.0]])
    x = torch.arange(8.0)
    frame = (a * (x + 0.5 + 0.25)).view(1, 1, 1, 8).expand(1, 1, 4, 8)
    target = unjitter(frame, jitter, scale=2)
    assert target.shape == (1, 1, 8, 16)
    q = torch.arange(16.0)
    # Target pixel q takes render sample floor((q + 0.5) / 2 - 0.25) = floor(q / 2) ...
    torch.testing.assert_close(target[0, 0, 0], a * (torch.floor(q / 2) + 0.75))
    # ... whose sample sits exactly on the centre of every odd target pixel: there the ramp is exact.
    torch.testing.assert_close(target[0, 0, 0, 1::2], a * (q[1::2] + 0.5) / 2)
    assert torch.equal(target, target[:, :, :1].expand_as(target))  # no vertical change

    # Any jitter: every target pixel's sample lies within half a render pixel of its centre (away from borders).
    jitter = torch.tensor([[0.3, -0.45]])
    offsets = sample_offsets(jitter, 6, 6, scale=2)
    interior = offsets[..., 1:-1, 1:-1]
    assert (interior >= -0.5).all() and (interior < 0.5).all()
    positions = torch.arange(6.0) + 0.5
    ramp = (positions + 0.3).view(1, 1, 1, 6).expand(1, 1, 6, 6)  # the sample's own x position
    centres_x = ((torch.arange(12.0) + 0.5) / 2).view(1, 1, 1, 12)
    torch.testing.assert_close(unjitter(ramp, jitter, 2) - centres_x, offsets[:, 0:1])


def test_sample_offsets_closed_form_and_scale_1_is_identity():
    offsets = sample_offsets(torch.tensor([[0.25, 0.0]]), 2, 2, scale=2)
    # x: even target pixels are half a render pixel left of their sample, odd ones sit on it; y (no jitter):
    # the sample is at the render pixel centre, a quarter render pixel below/above the target centres.
    torch.testing.assert_close(offsets[0, 0, 0], torch.tensor([0.5, 0.0, 0.5, 0.0]))
    torch.testing.assert_close(offsets[0, 1, :, 0], torch.tensor([0.25, -0.25, 0.25, -0.25]))
    image = torch.rand(1, 3, 5, 5)
    torch.testing.assert_close(unjitter(image, torch.tensor([[0.4, -0.3]]), scale=1), image)
    torch.testing.assert_close(sample_offsets(torch.tensor([[0.4, -0.3]]), 5, 5, 1),
                               torch.tensor([0.4, -0.3]).view(1, 2, 1, 1).expand(1, 2, 5, 5))


def test_history_is_read_at_the_pixel_centre_plus_the_motion_in_target_pixels():
    # History ramp over target pixels: value = x position of the pixel centre.
    frame = static_frame(size=8, jitter=(0.25, 0.0))
    frame.motion = torch.zeros(1, 2, 8, 8)
    frame.motion[:, 0] = 1.25  # 1.25 render pixels to the right in the previous frame
    depth, normal = torch.full((1, 1, 16, 16), 2.0), torch.zeros(1, 3, 16, 16)
    normal[:, 2] = 1.0
    centres = (torch.arange(16.0) + 0.5).view(1, 1, 1, 16).expand(1, 1, 16, 16)
    state = {name: centres.expand(1, c, 16, 16).clone() for name, c in HISTORY_CHANNELS.items()}
    state.update(depth=depth.clone(), normal=normal.clone())
    history, valid = reproject_history(frame, state, 2, depth, normal)
    # Read at centre + 2 * motion = centre + 2.5 target pixels, the jitter left out (the history is unjittered);
    # bilinear is exact on a ramp.
    expected = centres + 2.5
    inside = expected[0, 0, 0] < 16
    assert torch.equal(valid[0, 0, 0], inside)
    torch.testing.assert_close(history["output"][0, 0, 0, inside], expected[0, 0, 0, inside])
    assert (history["output"][0, 0, 0, ~inside] == 0).all()  # off-image reads have no history

    empty, none_valid = reproject_history(frame, None, 2, depth, normal)
    assert not none_valid.any() and all((t == 0).all() for t in empty.values())

    # A different surface in the previous frame (twice as far): the geometry test drops all history.
    state["depth"] = depth * 2
    history, valid = reproject_history(frame, state, 2, depth, normal)
    assert not valid.any() and (history["output"] == 0).all()


def test_update_sample_count_closed_form():
    alpha = torch.tensor([1.0, 0.5, 0.25, 0.0, 0.5]).view(1, 1, 1, 5)
    history = torch.tensor([7.0, 3.0, 3.0, MAX_COUNT, 3.0]).view(1, 1, 1, 5)
    valid = torch.tensor([True, True, True, True, False]).view(1, 1, 1, 5)
    count = update_sample_count(alpha, history, valid)
    torch.testing.assert_close(count.flatten(), torch.tensor([1.0, 2.5, 3.25, MAX_COUNT, 1.0]))


# ---------------------------------------------------------------------------------------------------------------
# Building blocks


def test_sinusoidal_encoding_closed_form():
    value = torch.tensor([0.0, math.pi / 2, 3.0]).view(1, 1, 1, 3)
    encoded = sinusoidal_encoding(value, channels=4, base=100.0)
    assert encoded.shape == (1, 4, 1, 3)
    # Channels: sin(v), cos(v), sin(v / 10), cos(v / 10)  (base^(2 * 1 / 4) = 10).
    for i, v in enumerate(value.flatten().tolist()):
        expected = torch.tensor([math.sin(v), math.cos(v), math.sin(v / 10), math.cos(v / 10)])
        torch.testing.assert_close(encoded[0, :, 0, i], expected)
    torch.testing.assert_close(encoded[0, :, 0, 1], torch.tensor([1.0, 0.0, math.sin(math.pi / 20),
                                                                  math.cos(math.pi / 20)]))
    with pytest.raises(ValueError):
        sinusoidal_encoding(value, channels=3, base=100.0)


def test_partial_convolution_convolves_only_the_first_channels():
    conv = PartialConv2d(channels=4, conv_channels=2, kernel_size=3)
    with torch.no_grad():
        conv.conv.weight.zero_()
        conv.conv.weight[0, 0] = 1.0  # output 0: 3x3 box sum of input 0
        conv.conv.weight[1, 1, 1, 1] = 2.0  # output 1: 2 * input 1 (centre tap only)
        conv.conv.bias.copy_(torch.tensor([0.0, 1.0]))
    x = torch.randn(1, 4, 5, 5)
    out = conv(x)
    assert out.shape == x.shape
    assert torch.equal(out[:, 2:], x[:, 2:])  # passed through untouched
    torch.testing.assert_close(out[:, 1], 2 * x[:, 1] + 1)
    box = torch.nn.functional.pad(x[:, 0:1], (1, 1, 1, 1)).unfold(2, 3, 1).unfold(3, 3, 1).sum(dim=(-1, -2))
    torch.testing.assert_close(out[:, 0:1], box)
    assert sum(p.numel() for p in conv.parameters()) == 2 * 2 * 9 + 2  # a quarter of a full 4 -> 4 conv


def test_affinity_kernels_are_a_gaussian_of_feature_distance():
    features = torch.zeros(1, 2, 3, 3)
    features[0, :, 1, 2] = torch.tensor([1.0, 1.0])  # right neighbour of the centre, squared distance 2
    bandwidth = torch.full((1, 1, 3, 3), 0.5)
    confidence = torch.zeros(1, 1, 3, 3)
    confidence[0, 0, 0, 1] = 3.0  # the pixel above the centre
    logits = affinity_kernel_logits(features, bandwidth, confidence)[0, :, 1, 1]
    expected = torch.zeros(9)
    expected[5] = -0.5 * 2.0  # tap (dx, dy) = (1, 0)
    expected[1] = 3.0  # tap (0, -1)
    torch.testing.assert_close(logits, expected)


def test_partitioning_pyramid_keeps_constants_and_reduces_to_one_level():
    image = torch.full((1, 2, 12, 10), 3.0)
    kernels = [torch.randn(1, 9, h, w) for h, w in ((12, 10), (6, 5), (3, 3), (2, 2))]
    partitions = torch.softmax(torch.randn(1, 4, 1, 1), dim=1).expand(1, 4, 12, 10)
    torch.testing.assert_close(partitioning_pyramid_filter(image, partitions, kernels), image)

    image = torch.rand(1, 2, 12, 10)
    only_finest = torch.zeros(1, 4, 12, 10)
    only_finest[:, 0] = 1.0
    torch.testing.assert_close(partitioning_pyramid_filter(image, only_finest, kernels),
                               apply_pixel_kernels(image, kernels[0], 3, normalize="softmax"))
