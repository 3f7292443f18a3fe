"""JNDS: registry and presets, shapes at scales 1 and 2, history and camera cuts, warping without jitter, the
lobe fallback, clamped linear kernels, the composite loss, gradients (float32 and QAT), int8 conversion
against the fake-quantized model, and a short overfit."""

import copy
import dataclasses
import functools

import pytest
import torch
import torch.nn.functional as F

from model.methods.base import FrameBatch
from model.methods.jnds import (
    ALL_PRESETS,
    INT8_SUFFIX,
    JNDS,
    PRESETS,
    TAPS,
    compress_hdr,
    hierarchical_filter,
    linear_kernel_weights,
    pack_pixels,
    unpack_pixels,
    warp_history,
)
from model.methods.quantization import convert_to_int8, has_fake_quantization
from model.methods.registry import build_method, example_batch, flops_per_pixel, method_spec
from tests.builders import static_frame as _static_frame
from tests.model.methods.overfitting import overfit_l1

# A static scene, diffuse + specular, both set.
static_frame = functools.partial(_static_frame, split=True)

# Int8 output against the fake-quantized (QAT) model it was converted from. QAT rounds weights and every
# convolution's output as int8 does, but not the outputs of pooling and bilinear resizing, which int8 rounds to
# the grid of their input: a few quantization steps of feature drift, measured at 16x16 up to 0.5% mean and 3%
# of the largest output value at scale 2 (0.05% / 0.5% at scale 1).
INT8_MEAN_TOLERANCE = 0.01  # mean |int8 - QAT| / mean |QAT|
INT8_MAX_TOLERANCE = 0.05  # max |int8 - QAT| / max |QAT|


def calibrated_qat(preset: str, scale: int, frames: list[FrameBatch]) -> JNDS:
    """A QAT model whose observers saw ``frames`` (training mode, no gradients), returned in eval mode."""
    method = build_method(f"jnds:{preset}{INT8_SUFFIX}", scale)
    with torch.no_grad():
        state = None
        for frame in frames:
            _, state = method.step(frame, state)
    return method.eval()


def run(method: JNDS, frames: list[FrameBatch]) -> list[torch.Tensor]:
    outputs, state = [], None
    with torch.no_grad():
        for frame in frames:
            output, state = method.step(frame, state)
            outputs.append(output)
    return outputs


def test_registry_entry_and_loss_weights():
    spec = method_spec("jnds")
    assert spec.learned and spec.scales == (1, 2) and spec.default_preset == "s"
    assert spec.presets == ("xs", "s", "m", "l", "xs-int8", "s-int8", "m-int8", "l-int8") == ALL_PRESETS
    method = build_method("jnds", scale=2)
    assert isinstance(method, JNDS) and method.preset == "s" and not method.quantized
    assert method.loss_weights == (0.2, 0.8)  # the paper's w_spatial = 0.2, w_temporal = 0.8
    int8 = build_method("jnds:s-int8", scale=2)
    assert int8.quantized and has_fake_quantization(int8) and int8.label == "jnds:s-int8"
    with pytest.raises(KeyError, match="no preset"):
        build_method("jnds:xxl")


def test_presets_grow_and_the_small_ones_fit_cpu_training():
    counts, flops = [], []
    for preset in PRESETS:
        method = build_method(f"jnds:{preset}", scale=2).eval()
        counts.append(method.parameter_count())
        flops.append(flops_per_pixel(method, 16, 16))
    assert counts == sorted(counts) and flops == sorted(flops)
    assert counts[0] < 25_000 and counts[1] < 60_000  # xs, s: a few tens of thousands of parameters
    # The int8 preset is the same network: the same parameters, plus quantizer buffers only.
    assert build_method("jnds:s-int8").parameter_count() == build_method("jnds:s").parameter_count()


@pytest.mark.parametrize("preset", ALL_PRESETS)
def test_every_preset_gives_finite_output_at_both_scales(preset):
    frame = example_batch(16, 16)
    for scale, size in ((2, 32), (1, 16)):
        method = build_method(f"jnds:{preset}", scale=scale).eval()
        with torch.no_grad():
            first, state = method.step(frame, None)  # the first step starts the history
            second, state = method.step(frame, state)
        for output in (first, second):
            assert output.shape == (1, 3, size, size)
            assert torch.isfinite(output).all() and (output >= 0).all()
        assert state["output"].shape == (1, 3, size, size) and state["diffuse"].shape == (1, 3, 16, 16)
        assert set(state) == {"diffuse", "specular", "albedo", "normal", "output", "history"}


def test_odd_sizes_and_batches():
    method = build_method("jnds:l", scale=2).eval()
    frame = example_batch(13, 18, batch=2)
    with torch.no_grad():
        output, state = method.step(frame, None)
        output, _ = method.step(frame, state)
    assert output.shape == (2, 3, 26, 36) and torch.isfinite(output).all()


def test_history_changes_the_output_and_a_cut_resets_only_its_sample():
    method = build_method("jnds:xs", scale=2).eval()
    frames = [static_frame(batch=2, seed=s) for s in range(3)]
    cut = dataclasses.replace(frames[2], camera_cut=torch.tensor([True, False]))
    continued = run(method, frames)[-1]
    with_cut = run(method, frames[:2] + [cut])[-1]
    fresh = run(method, [frames[2]])[-1]  # the same frame with no history at all
    torch.testing.assert_close(with_cut[0], fresh[0], atol=1e-5, rtol=1e-5)  # history dropped
    torch.testing.assert_close(with_cut[1], continued[1])  # the other sample keeps it
    assert (continued[1] - fresh[1]).abs().max() > 1e-3  # and history does matter


def test_training_state_carries_the_native_composite():
    method = build_method("jnds:xs", scale=2).train()
    _, state = method.step(example_batch(16, 16), None)
    assert state["composite"].shape == (1, 3, 16, 16) and state["history"].shape == (1, 1, 1, 1)
    method.eval()
    with torch.no_grad():
        _, state = method.step(example_batch(16, 16), None)
    assert "composite" not in state


def test_history_is_read_at_centre_plus_motion_without_the_jitter():
    history = torch.rand(1, 3, 32, 32)
    static = torch.zeros(1, 2, 16, 16)
    # A static camera: whatever the jitter, the pixel-centred history comes back unchanged.
    warped, inside = warp_history(history, static, scale=2)
    torch.testing.assert_close(warped, history, atol=1e-5, rtol=0)
    assert inside.all()
    # One render pixel of motion to the right is two target pixels: output x reads history x + 2.
    motion = torch.zeros(1, 2, 16, 16)
    motion[:, 0] = 1.0
    warped, inside = warp_history(history, motion, scale=2)
    torch.testing.assert_close(warped[..., :30], history[..., 2:], atol=1e-5, rtol=0)
    assert not inside[..., 30:].any() and inside[..., :30].all()


def test_jitter_is_a_network_input():
    method = build_method("jnds:xs", scale=2).eval()
    plain = run(method, [static_frame(seed=s) for s in range(2)])
    jittered = run(method, [static_frame(seed=s, jitter=(0.25, -0.25)) for s in range(2)])
    assert not torch.allclose(plain[1], jittered[1])  # an input: the network may place samples by it


def test_missing_lobe_split_falls_back_to_diffuse_is_color():
    frame = static_frame()
    without = dataclasses.replace(frame, diffuse=None, specular=None)
    explicit = dataclasses.replace(frame, diffuse=frame.color, specular=torch.zeros_like(frame.color))
    method = build_method("jnds:xs", scale=2).eval()
    torch.testing.assert_close(run(method, [without])[0], run(method, [explicit])[0])
    # Roughness is optional too (defaults to 1).
    assert torch.isfinite(run(method, [dataclasses.replace(frame, roughness=None)])[0]).all()


def test_step_never_reads_the_reference():
    frame = dataclasses.replace(example_batch(16, 16), reference=torch.full((1, 3, 32, 32), float("nan")))
    output = run(build_method("jnds:xs", scale=2).eval(), [frame])[0]
    assert torch.isfinite(output).all()


def test_kernel_weights_are_linear_and_clamped_to_unit_range():
    raw = torch.tensor([-5.0, -1.0, -0.3, 0.0, 0.7, 1.0, 4.0])
    assert torch.equal(linear_kernel_weights(raw), torch.tensor([-1.0, -1.0, -0.3, 0.0, 0.7, 1.0, 1.0]))
    # Inside a filter path: out-of-range predictions act exactly like their clamped values.
    image, history = torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8)
    native = torch.randn(1, 29, 8, 8) * 3
    levels = [torch.randn(1, 19, 4, 4) * 3, torch.randn(1, TAPS, 2, 2) * 3]

    def clamped(head: torch.Tensor, kernel_channels: list[slice]) -> torch.Tensor:
        head = head.clone()
        for channels in kernel_channels:
            head[:, channels] = head[:, channels].clamp(-1, 1)
        return head

    native_clamped = clamped(native, [slice(0, 18), slice(19, 28)])  # spatial, temporal, upsampling kernels
    levels_clamped = [clamped(levels[0], [slice(0, 18)]), clamped(levels[1], [slice(0, 9)])]
    ok = torch.ones(1, 1, 1, 1)
    expected = hierarchical_filter(image, history, ok, native_clamped, levels_clamped)
    torch.testing.assert_close(hierarchical_filter(image, history, ok, native, levels), expected)
    assert (expected >= 0).all()  # every filter of the path ends in a ReLU


def test_an_untrained_model_starts_as_a_smoothing_pass_through():
    # Head weights start small around box / identity kernels: constant input comes out (nearly) constant.
    frame = static_frame()
    flat = torch.full_like(frame.color, 0.4)
    frame = dataclasses.replace(frame, color=flat, diffuse=flat, specular=torch.zeros_like(flat))
    output = run(build_method("jnds:s", scale=2).eval(), [frame])[0]
    interior = output[..., 4:-4, 4:-4]
    assert (interior - 0.4).abs().max() < 0.15


def test_compress_hdr_is_eq_1_with_a_finite_slope_at_zero():
    x = torch.tensor([0.0, 0.5, 3.0, 1e6], requires_grad=True)
    y = compress_hdr(x)
    expected = torch.log1p(x.detach().clamp(0, 65535)) ** (1 / 2.2)
    assert y[0] == 0 and torch.allclose(y, expected, atol=0.006)
    y.sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad[3] == 0  # clamped at 65535


def test_pixel_packing_matches_torch_shuffles():
    image = torch.rand(2, 7, 12, 10)
    for channels_last in (False, True):
        packed = pack_pixels(image, 2, channels_last=channels_last)
        assert torch.equal(packed, F.pixel_unshuffle(image, 2))
        assert packed.is_contiguous(memory_format=torch.channels_last) == channels_last
    assert torch.equal(unpack_pixels(F.pixel_unshuffle(image, 2), 2), image)


def test_auxiliary_loss_supervises_the_native_composite():
    method = build_method("jnds:xs", scale=2).train()
    frames = [dataclasses.replace(static_frame(seed=s), reference=torch.rand(1, 3, 32, 32)) for s in range(2)]
    states, state = [], None
    for frame in frames:
        _, state = method.step(frame.without_reference(), state)
        states.append(state)
    loss = method.auxiliary_loss(frames, states)
    assert loss.dim() == 0 and torch.isfinite(loss) and loss > 0
    # A composite equal to the box-filtered reference costs nothing.
    perfect = [dict(s, composite=F.avg_pool2d(f.reference, 2)) for s, f in zip(states, frames)]
    assert method.auxiliary_loss(frames, perfect).item() == pytest.approx(0.0, abs=1e-6)
    assert method.auxiliary_loss([f.without_reference() for f in frames], states) is None


@pytest.mark.parametrize("preset", ["xs", "xs-int8"])
def test_gradients_reach_every_parameter_through_two_unrolled_steps(preset):
    method = build_method(f"jnds:{preset}", scale=2).train()
    target = torch.rand(1, 3, 32, 32)
    state, loss = None, torch.zeros(())
    for seed in (1, 2):
        output, state = method.step(example_batch(16, 16, seed=seed), state)
        loss = loss + (output - target).abs().mean()
    loss.backward()
    for name, p in method.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


@pytest.mark.parametrize("preset, scale", [("xs", 2), ("s", 2), ("s", 1)])
def test_int8_conversion_is_close_to_the_fake_quantized_model(preset, scale):
    frames = [example_batch(16, 16, seed=s) for s in range(4)]
    qat = calibrated_qat(preset, scale, frames)
    int8 = copy.deepcopy(qat).for_inference()
    assert int8.is_int8 and not qat.is_int8 and not int8.training
    kinds = {type(m).__module__ for m in int8.network.modules()}
    assert any(kind.startswith("torch.ao.nn.intrinsic.quantized") for kind in kinds)  # int8 conv + ReLU
    for expected, got in zip(run(qat, frames[:2]), run(int8, frames[:2]), strict=True):
        difference = (got - expected).abs()
        assert torch.isfinite(got).all()
        assert difference.mean() <= INT8_MEAN_TOLERANCE * expected.abs().mean()
        assert difference.max() <= INT8_MAX_TOLERANCE * expected.abs().max()


def test_int8_model_reports_the_parameters_and_flops_of_its_float_network():
    from model.methods.registry import flops_per_pixel

    frames = [example_batch(16, 16, seed=s) for s in range(3)]
    int8 = calibrated_qat("xs", 2, frames).for_inference()
    float_method = build_method("jnds:xs", scale=2)
    assert int8.is_int8
    # Packed int8 weights are not torch parameters and the FLOP counter skips quantized kernels.
    assert sum(p.numel() for p in int8.parameters()) < float_method.parameter_count()
    assert int8.parameter_count() == float_method.parameter_count()
    assert flops_per_pixel(int8) == pytest.approx(flops_per_pixel(float_method))


def test_int8_needs_calibration_and_float_weights_load_into_qat():
    float_method = build_method("jnds:xs", scale=2)
    qat = build_method("jnds:xs-int8", scale=2)
    qat.load_float_weights(float_method.state_dict())
    with pytest.raises(ValueError, match="not seen any data"):
        convert_to_int8(copy.deepcopy(qat).network)
    with pytest.warns(UserWarning, match="not seen any data"):  # evaluating an untrained int8 preset still runs
        assert not copy.deepcopy(qat).for_inference().is_int8
    frames = [example_batch(16, 16, seed=s) for s in range(3)]
    with torch.no_grad():
        state = None
        for frame in frames:
            _, state = qat.step(frame, state)
    qat.eval()
    # Same weights: fake quantization moves the output a little, not a lot.
    expected, got = run(float_method.eval(), frames)[-1], run(qat, frames)[-1]
    assert (got - expected).abs().mean() < 0.05 * expected.abs().mean()
    with pytest.raises(ValueError, match="int8 preset"):
        float_method.load_float_weights(qat.state_dict())


def test_qat_state_dict_with_its_ranges_round_trips_through_a_fresh_model():
    frames = [example_batch(16, 16, seed=s) for s in range(3)]
    qat = calibrated_qat("xs", 2, frames)
    fresh = build_method("jnds:xs-int8", scale=2)
    fresh.load_state_dict(qat.state_dict())  # strict: checkpoints of QAT runs reload and resume
    fresh.eval()
    torch.testing.assert_close(run(fresh, frames)[-1], run(qat, frames)[-1])
    assert copy.deepcopy(fresh).for_inference().is_int8


def test_float_for_inference_is_the_same_model_in_eval_mode():
    method = build_method("jnds:xs", scale=2).eval()
    frame = example_batch(16, 16)
    expected = run(method, [frame])[0]
    fast = copy.deepcopy(method).for_inference()
    assert not fast.training
    torch.testing.assert_close(run(fast, [frame])[0], expected)


def test_short_overfit_reduces_l1_loss():
    # One fixed pair: a noisy 16x16 render of a flat grey wall under a checkerboard of light, and its clean
    # 32x32 reference. Lower L1 means kernels learned to denoise and to put the checker edges back.
    size = 16
    ys, xs = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    clean = 0.5 * (0.2 + 0.8 * ((xs // 4 + ys // 4) % 2)).expand(1, 3, 32, 32).contiguous()
    noise = torch.rand(1, 3, size, size, generator=torch.Generator().manual_seed(3)) * 2
    noisy = F.avg_pool2d(clean, 2) * noise
    frame = dataclasses.replace(static_frame(size=size), color=noisy, diffuse=noisy, specular=torch.zeros_like(noisy))
    method = build_method("jnds:s", scale=2).train()
    initial, final = overfit_l1(method, frame, clean, lr=1e-2)
    assert final <= 0.7 * initial, (initial, final)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_step_matches_cpu_and_int8_stays_fake_quantized_there():
    method = build_method("jnds:s", scale=2).eval()
    frames = [static_frame(batch=2, seed=0), static_frame(batch=2, seed=1, cut=[True, False])]
    outputs = {}
    for device in ("cpu", "cuda"):
        moved = copy.deepcopy(method).to(device)
        outputs[device] = run(moved, [frame.to(device) for frame in frames])[-1].cpu()
    torch.testing.assert_close(outputs["cuda"], outputs["cpu"], atol=1e-4, rtol=1e-4)
    qat = calibrated_qat("xs", 2, frames).to("cuda").for_inference()
    assert not qat.is_int8 and torch.isfinite(run(qat, [f.to("cuda") for f in frames])[-1]).all()
