"""The fused family: OIDN's estimate as the fallback, TAA as the starting point, history reuse that can learn."""

from __future__ import annotations

import dataclasses

import pytest
import torch
import torch.nn.functional as F

from model.methods.base import FrameBatch
from model.methods.fused import (ALBEDO_DETAIL_KEY, KERNEL, KERNEL_LIMIT_KEY, LEGACY_CANDIDATES, MEAN_FRAMES,
                                 MEAN_WINDOW_KEY,
                                 RECURRENCE_KEY, SAMPLE_MEAN_KEY, SAMPLE_MEAN_TRUST_KEY, STALE_REGION_KEY,
                                 STALE_TEST_KEY, UNJITTER_KEY, Fused, frame_samples, sample_mean_resample,
                                 unjittered_resample)
from model.methods.oidn import oidn_denoise
from model.methods.oidn_taa import reinhard, reinhard_inverse
from model.methods.registry import build_method, example_batch, inference_cost, method_spec
from model.ops.rectify import variance_clip
from tests.builders import noisy_constant, plane_frame, static_frame

SIZE = 16


def truth() -> torch.Tensor:
    ramp = torch.linspace(0.2, 0.8, SIZE).view(1, 1, 1, SIZE).expand(1, 1, SIZE, SIZE)
    return (ramp * torch.tensor([1.0, 0.8, 0.6]).view(1, 3, 1, 1)).contiguous()


def frame_with_estimate(estimate: torch.Tensor, **kwargs):
    frame = plane_frame(noisy_constant(truth(), torch.Generator().manual_seed(0)), **kwargs)
    frame.spatial_estimate = estimate
    return frame


def test_registered_as_learned_with_oidn_quality_presets_at_both_scales():
    spec = method_spec("fused")
    assert spec.presets == ("fast", "balanced", "high") and spec.default_preset == "balanced" and spec.learned
    for scale in (1, 2):
        method = build_method("fused:fast", scale)
        assert method.spatial_prior == "fast"
        output, state = method.step(plane_frame(truth()), None)
        assert output.shape == (1, 3, SIZE * scale, SIZE * scale) and torch.isfinite(output).all()
        assert state["history"].shape[-1] == SIZE * scale and state["hidden"].shape[-1] == SIZE
    parameters, flops = inference_cost(build_method("fused"))
    assert 10_000 < parameters < 100_000 and flops > 0
    with pytest.raises(KeyError, match="presets"):
        Fused("ultra")


def test_without_history_the_output_is_the_spatial_estimate():
    estimate = truth() * 1.1
    output, _ = build_method("fused").step(frame_with_estimate(estimate), None)
    # The kernel starts as (almost) the identity and there is nothing else to fuse with.
    torch.testing.assert_close(output, estimate, atol=0.01, rtol=0.01)


def test_without_a_precomputed_estimate_it_runs_oidn_itself():
    frame = plane_frame(noisy_constant(truth(), torch.Generator().manual_seed(1)))
    output, _ = build_method("fused:fast").step(frame, None)
    # The near-identity kernel (0.993 on the centre) leaks a little of OIDN's neighbours: compare on average.
    assert float((output - oidn_denoise(frame, "fast")).abs().mean()) < 0.005


def test_an_untrained_model_starts_from_taa_weights():
    first = frame_with_estimate(truth())
    second = frame_with_estimate(truth() * 0.9)
    method = build_method("fused")
    out1, state = method.step(first, None)
    out2, _ = method.step(second, state)
    current = reinhard(truth() * 0.9)
    taa = 0.2 * current + 0.8 * variance_clip(reinhard(out1), current)
    torch.testing.assert_close(out2, reinhard_inverse(taa), atol=0.01, rtol=0.02)


def test_history_is_dropped_on_a_cut_and_where_depth_fails():
    method = build_method("fused")
    _, state = method.step(frame_with_estimate(truth() * 3), None)
    for frame in (frame_with_estimate(truth(), camera_cut=[True]),
                  frame_with_estimate(truth(), depth=torch.full((1, 1, SIZE, SIZE), 4.0))):
        output, _ = method.step(frame, state)
        torch.testing.assert_close(output, truth(), atol=0.01, rtol=0.01)


def test_unjittered_resample_puts_a_jittered_sample_back_at_its_position():
    # A linear ramp sampled at x + 0.5 + jx: reading it back at P - jx gives the ramp at the target centres P.
    jitter = torch.tensor([[0.3, -0.2]])
    xs = torch.arange(8, dtype=torch.float64) + 0.5 + 0.3
    image = (0.05 * xs).view(1, 1, 1, 8).expand(1, 3, 8, 8).contiguous()
    resampled = unjittered_resample(image, jitter.double(), 2)
    centres = (torch.arange(16, dtype=torch.float64) + 0.5) / 2
    # torch's bicubic (A = -0.75) reproduces a ramp to within 0.03 px; ignoring the jitter would be 0.3 px off.
    error_px = (resampled[0, 0, 4, 4:-4] / 0.05 - centres[4:-4]).abs()
    assert float(error_px.max()) < 0.03
    ignored = unjittered_resample(image, torch.zeros(1, 2, dtype=torch.float64), 2)
    assert float((ignored[0, 0, 4, 4:-4] / 0.05 - centres[4:-4]).abs().min()) > 0.25


def test_a_sample_mean_estimate_is_read_at_its_frames_mean_jitter():
    # One frame: at its own jitter, as unjittered_resample. Two: halfway between that read and the centred one.
    jitter = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
    xs = torch.arange(8, dtype=torch.float64) + 0.5
    image = (0.05 * xs).view(1, 1, 1, 8).expand(1, 3, 8, 8).contiguous()
    at_jitter = unjittered_resample(image, jitter, 2)
    centred = unjittered_resample(image, torch.zeros_like(jitter), 2)
    one, two = (torch.full((1, 1, 8, 8), n, dtype=torch.float64) for n in (1.0, 2.0))
    torch.testing.assert_close(sample_mean_resample(image, jitter, one, 2), at_jitter)
    torch.testing.assert_close(sample_mean_resample(image, jitter, two, 2), (at_jitter + centred) / 2)
    assert float((at_jitter - centred).abs().max()) > 0.01  # the two reads differ: the test can tell them apart


def test_at_1x_the_unjittered_read_of_one_frame_is_the_bicubic_read_and_of_a_mean_part_of_it():
    # 1x: the centred read is the image itself, so a mean of two frames is halfway between it and the shifted read.
    generator = torch.Generator().manual_seed(5)
    image = torch.rand(1, 3, 8, 8, generator=generator, dtype=torch.float64)
    jitter = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
    at_jitter = unjittered_resample(image, jitter, 1)
    torch.testing.assert_close(at_jitter, _resample_by_grid_sample(image, jitter, 1))
    one, two = (torch.full((1, 1, 8, 8), n, dtype=torch.float64) for n in (1.0, 2.0))
    torch.testing.assert_close(sample_mean_resample(image, jitter, one, 1), at_jitter)
    torch.testing.assert_close(sample_mean_resample(image, jitter, two, 1), (at_jitter + image) / 2)
    assert torch.equal(unjittered_resample(image, torch.zeros_like(jitter), 1), image)


def _jittered_ramp_frame(jitter: tuple[float, float]) -> FrameBatch:
    """A frame whose estimate is the ramp of ``truth`` sampled at x + 0.5 + jitter, as OIDN's estimate of a jittered
    frame is."""
    xs = (torch.arange(SIZE, dtype=torch.float32) + jitter[0]).view(1, 1, 1, SIZE)
    ramp = (0.2 + 0.6 * xs / (SIZE - 1)).expand(1, 1, SIZE, SIZE) * torch.tensor([1.0, 0.8, 0.6]).view(1, 3, 1, 1)
    return frame_with_estimate(ramp.contiguous(), jitter=jitter)


def test_at_1x_the_unjittered_estimate_puts_a_jittered_frame_back_at_the_pixel_centres():
    frame = _jittered_ramp_frame((0.4, 0.0))
    plain, _ = build_method("fused:fast", 1).step(frame, None)
    method = build_method("fused:fast", 1)
    method.set_unjitter_estimate(True)
    unjittered, _ = method.step(frame, None)
    inside = (slice(None), slice(None), slice(None), slice(3, -3))  # bicubic reads two pixels on, clamped at the edge
    # An untrained head weighs its candidates alike everywhere: the output is made of the estimate it reads.
    torch.testing.assert_close(unjittered[inside], truth()[inside], atol=2e-3, rtol=2e-3)
    assert float((plain - truth())[inside].abs().min()) > 0.009  # as OIDN made it: 0.4 px off, 0.0096 in blue
    still = frame_with_estimate(truth())  # no jitter: the same output either way
    assert torch.equal(method.step(still, None)[0], build_method("fused:fast", 1).step(still, None)[0])


def test_the_unjitter_setting_is_recorded_always_on_at_2x_and_refused_unless_true_or_false():
    saved = build_method("fused:fast", 1)
    assert not saved.unjitter_estimate  # what every 1x model before the setting ran
    saved.set_unjitter_estimate(True)
    loaded = build_method("fused:fast", 1)
    loaded.load_state_dict(saved.state_dict())
    assert loaded.unjitter_estimate
    tuned = build_method("fused:fast", 1)
    tuned.load_initial_weights(saved.state_dict())  # --init-from keeps it
    assert tuned.unjitter_estimate
    loaded.load_state_dict({k: v for k, v in saved.state_dict().items() if k != UNJITTER_KEY})
    assert not loaded.unjitter_estimate
    two_x = build_method("fused:fast", 2)
    assert two_x.unjitter_estimate
    two_x.load_state_dict({k: v for k, v in two_x.state_dict().items() if k != UNJITTER_KEY})
    assert two_x.unjitter_estimate  # a 2x checkpoint from before the setting resampled as it does now
    with pytest.raises(ValueError, match="cannot be false at 2x"):
        two_x.set_unjitter_estimate(False)
    for value in (1, 0.0, "true", None):
        with pytest.raises(ValueError, match="true or false"):
            build_method("fused:fast", 1).set_unjitter_estimate(value)


def test_the_sample_mean_read_of_a_batch_is_each_items_own():
    # Its two reads run as one batch of twice the items: item i's reads must stay item i's, with its own jitter.
    generator = torch.Generator().manual_seed(3)
    image = torch.rand(3, 3, 8, 8, generator=generator)
    jitter = torch.tensor([[0.3, -0.2], [-0.4, 0.1], [0.0, 0.45]])
    count = torch.stack([torch.full((1, 8, 8), n) for n in (1.0, 2.0, 5.0)])
    together = sample_mean_resample(image, jitter, count, 2)
    for i in range(3):
        alone = sample_mean_resample(image[i:i + 1], jitter[i:i + 1], count[i:i + 1], 2)
        assert torch.equal(together[i:i + 1], alone)


def test_training_teaches_it_to_trust_a_static_history():
    # A static scene whose spatial estimate is wrong by a different random amount every frame (like OIDN's
    # blotches): averaging over time is the answer, which the TAA start only partly does.
    generator = torch.Generator().manual_seed(2)
    frames = [frame_with_estimate(truth() * (1 + 0.3 * (torch.rand(1, 1, SIZE, SIZE, generator=generator) - 0.5)))
              for _ in range(6)]
    torch.manual_seed(0)
    method = build_method("fused")
    optimizer = torch.optim.Adam(method.parameters(), lr=3e-3)

    def last_frame_error() -> torch.Tensor:
        state = None
        for frame in frames:
            output, state = method.step(frame, state)
        return (output - truth()).abs().mean()

    with torch.no_grad():
        initial = last_frame_error().item()
    for _ in range(40):
        optimizer.zero_grad()
        last_frame_error().backward()
        optimizer.step()
    with torch.no_grad():
        final = last_frame_error().item()
    assert final < 0.8 * initial, (initial, final)


def test_the_inference_form_gives_the_training_forms_output():
    torch.manual_seed(3)
    trained = build_method("fused", 2)
    for parameter in trained.parameters():  # away from the initial head, so every path matters
        parameter.data += 0.05 * torch.randn_like(parameter)
    import copy
    fast = copy.deepcopy(trained).for_inference()
    frames = [frame_with_estimate(truth() * (1 + 0.1 * k)) for k in range(3)]
    state_a = state_b = None
    with torch.no_grad():
        for frame in frames:
            out_a, state_a = trained.eval().step(frame, state_a)
            out_b, state_b = fast.step(frame, state_b)
    torch.testing.assert_close(out_b, out_a, atol=1e-5, rtol=1e-4)


def test_the_inference_form_steps_alike_with_gradients_on():
    # without gradients its input is written straight into channels_last memory, with them concatenated and copied
    torch.manual_seed(4)
    fast = build_method("fused", 2).for_inference()
    frames = [frame_with_estimate(truth() * (1 + 0.1 * k)) for k in range(2)]
    outputs = []
    for grad in (False, True):
        state = None
        with torch.set_grad_enabled(grad):
            for frame in frames:
                output, state = fast.step(frame, state)
        outputs.append(output.detach())
    assert torch.equal(outputs[0], outputs[1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("scale", [1, 2])
def test_a_gpu_stream_gives_the_cpu_streams_output(scale):
    """The whole step on a GPU, OIDN included (its CUDA device where pyoidn has one): output and history stay there."""
    torch.manual_seed(3)
    method = build_method("fused:fast", scale)
    for parameter in method.parameters():
        parameter.data += 0.05 * torch.randn_like(parameter)
    method = method.eval().for_inference()
    import copy
    on_gpu = copy.deepcopy(method).to("cuda")
    state_cpu = state_gpu = None
    with torch.no_grad():
        for seed in range(3):
            out_cpu, state_cpu = method.step(example_batch(SIZE, SIZE, seed=seed), state_cpu)
            out_gpu, state_gpu = on_gpu.step(example_batch(SIZE, SIZE, seed=seed, device="cuda"), state_gpu)
            assert out_gpu.device.type == "cuda" and state_gpu["history"].device.type == "cuda"
            # OIDN's CUDA and CPU devices agree to about 1e-2 (test_oidn); the network adds nothing to that.
            torch.testing.assert_close(out_gpu.cpu(), out_cpu, atol=3e-2, rtol=3e-2)


def test_resampling_next_to_a_bright_emitter_does_not_overshoot():
    image = torch.full((1, 3, 8, 8), 0.02)
    image[..., 3:5, 3:5] = 0.98  # x / (1 + x) of radiance 49: a visible light
    resampled = unjittered_resample(image, torch.tensor([[0.37, -0.41]]), 2)
    assert float(resampled.max()) <= 0.98 + 1e-6 and float(resampled.min()) >= 0.02 - 1e-6


def _resample_by_grid_sample(image, jitter, scale):
    # The resample as one full-grid grid_sample with 3x3 bounds from max_pool2d: what the separable form must equal.
    n, c, h, w = image.shape
    xs = (torch.arange(w * scale, dtype=image.dtype) + 0.5) / scale
    ys = (torch.arange(h * scale, dtype=image.dtype) + 0.5) / scale
    grid_x = xs.view(1, 1, -1) - jitter[:, 0].view(-1, 1, 1)
    grid_y = ys.view(1, -1, 1) - jitter[:, 1].view(-1, 1, 1)
    grid = torch.stack([(2 * grid_x / w - 1).expand(n, h * scale, w * scale),
                        (2 * grid_y / h - 1).expand(n, h * scale, w * scale)], dim=-1)
    resampled = F.grid_sample(image, grid, mode="bicubic", padding_mode="border", align_corners=False)
    padded = F.pad(image, (1, 1, 1, 1), mode="replicate")
    bounds = torch.cat([F.max_pool2d(padded, 3, stride=1), -F.max_pool2d(-padded, 3, stride=1)], dim=1)
    bounds = F.grid_sample(bounds, grid, mode="nearest", padding_mode="border", align_corners=False)
    return torch.minimum(torch.maximum(resampled, bounds[:, c:]), bounds[:, :c])


@pytest.mark.parametrize("scale", [1, 2, 3])
def test_the_jitter_resample_is_the_full_grid_one(scale):
    generator = torch.Generator().manual_seed(scale)
    image = torch.rand(3, 3, 12, 10, generator=generator)
    image[0, :, 4:6, 4:6] = 0.98  # a visible light: the bounds clamp the overshoot around it
    # Halton jitters land on quarters, where the nearest bounds pixel is a tie the two must break alike
    jitter = torch.tensor([[0.25, -0.25], [0.0, 0.5], [0.37, -0.41]])
    torch.testing.assert_close(unjittered_resample(image, jitter, scale), _resample_by_grid_sample(image, jitter, scale))


def legacy_state_dict(seed: int = 4) -> dict[str, torch.Tensor]:
    """A three-candidate network's weights (as checkpoints from before the running mean hold), off its initial
    head so every path matters."""
    torch.manual_seed(seed)
    legacy = build_method("fused")
    legacy.net = legacy._network(LEGACY_CANDIDATES)
    for parameter in legacy.parameters():
        parameter.data += 0.05 * torch.randn_like(parameter)
    return legacy.state_dict()


def test_the_running_mean_is_the_mean_of_the_spatial_estimates_while_history_holds():
    estimates = [truth() * (1 + 0.2 * k) for k in range(4)]
    method, state = build_method("fused"), None
    for estimate in estimates:
        _, state = method.step(frame_with_estimate(estimate), state)
    expected = torch.stack([reinhard(estimate) for estimate in estimates]).mean(dim=0)
    torch.testing.assert_close(state["mean"], expected, atol=1e-5, rtol=1e-5)
    assert float(state["count"].min()) == float(state["count"].max()) == 4.0
    # A cut restarts it at the current estimate.
    _, state = method.step(frame_with_estimate(truth(), camera_cut=[True]), state)
    torch.testing.assert_close(state["mean"], reinhard(truth()))
    assert float(state["count"].max()) == 1.0


def test_past_its_window_the_running_mean_is_an_exponential_average_of_the_window_s_length():
    estimates = [truth() * (1 + 0.1 * k) for k in range(6)]
    method, state = build_method("fused"), None
    method.set_mean_max_frames(3)
    for estimate in estimates:
        _, state = method.step(frame_with_estimate(estimate), state)
    values = [reinhard(estimate) for estimate in estimates]
    expected = sum(values[:3]) / 3  # 1 / n weights up to three frames
    for value in values[3:]:
        expected = expected + (value - expected) / 3  # then a third for each new frame
    torch.testing.assert_close(state["mean"], expected, atol=1e-5, rtol=1e-5)
    assert float(state["count"].max()) == 3.0


@pytest.mark.parametrize("value", [0, -3, 2.5, True])
def test_a_mean_window_that_is_not_a_whole_number_of_frames_is_refused(value):
    method = build_method("fused")
    with pytest.raises(ValueError, match="whole number of frames"):
        method.set_mean_max_frames(value)
    assert method.mean_max_frames == int(MEAN_FRAMES)


def test_a_checkpoint_from_before_the_running_mean_loads_as_the_network_it_was():
    weights = legacy_state_dict()
    method = build_method("fused")
    method.load_state_dict(weights)
    assert method.net.candidates == LEGACY_CANDIDATES and not method.has_mean
    frames = [frame_with_estimate(truth() * (1 + 0.1 * k)) for k in range(3)]
    state = None
    with torch.no_grad():
        for frame in frames:
            output, state = method.step(frame, state)
    assert "mean" not in state and torch.isfinite(output).all()
    with pytest.raises(ValueError, match="fusion candidates"):
        method.load_state_dict({**weights, "net.head.weight": weights["net.head.weight"][:-2]})


def test_init_from_an_older_checkpoint_starts_as_nearly_the_same_function():
    weights = legacy_state_dict()
    legacy = build_method("fused")
    legacy.load_state_dict(weights)
    grown = build_method("fused")
    grown.load_initial_weights(weights)
    assert grown.has_mean and not grown.history_before_kernel  # the recurrence comes with the weights
    frames = [frame_with_estimate(truth() * (1 + 0.3 * (k % 2))) for k in range(4)]
    state_a = state_b = None
    with torch.no_grad():
        for frame in frames:
            out_a, state_a = legacy.eval().step(frame, state_a)
            out_b, state_b = grown.eval().step(frame, state_b)
            # One new candidate at 1%, everything else as it was.
            assert float((out_b - out_a).abs().max()) < 0.02 * float(out_a.abs().max())
    # A legacy session's state (no running mean) continues on the new network.
    output, state = grown.step(frames[0], {k: v for k, v in state_a.items()})
    assert torch.isfinite(output).all() and float(state["count"].max()) == 1.0


def blurring(method: Fused) -> Fused:
    """The method with its kernels uniform (a 3 x 3 box blur), so the output differs from the fused blend."""
    per_pixel = method.net.candidates + KERNEL * KERNEL
    with torch.no_grad():
        method.net.head.bias[method.net.candidates:per_pixel] = 0.0
    return method


def checker() -> torch.Tensor:
    rows = torch.arange(SIZE).view(SIZE, 1)
    return (0.2 + 0.6 * ((rows + rows.T) % 2)).expand(1, 3, SIZE, SIZE).contiguous()


def total_variation(image: torch.Tensor) -> float:
    return float((image[..., 1:] - image[..., :-1]).abs().mean())


def test_the_history_is_the_blend_before_the_kernel_where_the_model_says_so():
    frame = frame_with_estimate(checker())
    new = blurring(build_method("fused"))
    new.set_history_before_kernel(True)
    output, state = new.step(frame, None)
    # The blend is the checker itself here (every candidate is it); the box kernel smooths only the output.
    assert total_variation(state["history"]) > 5 * total_variation(reinhard(output))
    torch.testing.assert_close(state["history"], reinhard(checker()), atol=0.02, rtol=0.02)
    old = blurring(build_method("fused"))
    old.load_state_dict({k: v for k, v in new.state_dict().items() if k != RECURRENCE_KEY})
    assert not old.history_before_kernel
    old_output, old_state = old.step(frame, None)
    torch.testing.assert_close(old_output, output)
    torch.testing.assert_close(old_state["history"], reinhard(old_output))


def test_a_checkpoint_records_the_recurrence_it_runs():
    assert not build_method("fused").history_before_kernel  # what every model is trained with
    saved = build_method("fused:fast", 2)
    for value in (False, True):
        saved.set_history_before_kernel(value)
        loaded = build_method("fused:fast", 2)
        loaded.load_state_dict(saved.state_dict())
        assert loaded.history_before_kernel is value and float(loaded.state_dict()[RECURRENCE_KEY]) == float(value)


def test_init_from_keeps_the_recurrence_of_the_checkpoint_it_starts_from():
    source = build_method("fused")
    source.set_history_before_kernel(True)
    tuned = build_method("fused")
    tuned.load_initial_weights(source.state_dict())
    assert tuned.history_before_kernel
    without_entry = {k: v for k, v in source.state_dict().items() if k != RECURRENCE_KEY}
    tuned.load_initial_weights(without_entry)  # a checkpoint from before the choice: the output was its history
    assert not tuned.history_before_kernel


def test_frames_above_the_kernel_limit_output_the_blend_unfiltered():
    frame = frame_with_estimate(checker())  # 16 x 16 = 256 render pixels
    method = blurring(build_method("fused"))
    filtered, _ = method.step(frame, None)
    assert total_variation(reinhard(filtered)) < 0.2 * total_variation(reinhard(checker()))
    method.set_kernel_max_pixels(255)
    method.set_history_before_kernel(True)
    unfiltered, state = method.step(frame, None)
    # The blend (here the checker itself: every candidate is it), and the history is that same image.
    torch.testing.assert_close(reinhard(unfiltered), reinhard(checker()), atol=0.02, rtol=0.02)
    torch.testing.assert_close(state["history"], reinhard(unfiltered))
    method.set_kernel_max_pixels(256)  # at the limit the kernel still runs
    torch.testing.assert_close(method.step(frame, None)[0], filtered)


@pytest.mark.parametrize("scale", [1, 2])
@pytest.mark.parametrize("setting, key, default, value", [
    pytest.param("kernel_max_pixels", KERNEL_LIMIT_KEY, 0, 32768, id="kernel limit"),  # default: every frame filtered
    pytest.param("mean_max_frames", MEAN_WINDOW_KEY, int(MEAN_FRAMES), 8, id="mean window"),
    pytest.param("stale_test_sigmas", STALE_TEST_KEY, 0.0, 2.0, id="stale-history test"),  # default: no test
    pytest.param("stale_region_pixels", STALE_REGION_KEY, 0, 33, id="regional stale-history test"),  # default: none
])
def test_a_checkpoint_records_its_run_time_setting_and_older_ones_load_with_the_default(scale, setting, key, default,
                                                                                        value):
    assert getattr(build_method("fused", scale), setting) == default  # as every shipped model was trained
    saved = build_method("fused:fast", scale)
    getattr(saved, f"set_{setting}")(value)
    loaded = build_method("fused:fast", scale)
    loaded.load_state_dict(saved.state_dict())
    assert getattr(loaded, setting) == value
    tuned = build_method("fused:fast", scale)
    tuned.load_initial_weights(saved.state_dict())  # --init-from keeps it
    assert getattr(tuned, setting) == value
    loaded.load_state_dict({k: v for k, v in saved.state_dict().items() if k != key})
    assert getattr(loaded, setting) == default and float(loaded.state_dict()[key]) == float(default)


@pytest.mark.parametrize("value", [-1, 2.5, True])
def test_a_kernel_limit_that_is_not_a_whole_number_of_pixels_is_refused(value):
    with pytest.raises(ValueError, match="whole number of pixels"):
        build_method("fused").set_kernel_max_pixels(value)


HISTORY, CLIPPED_MEAN = 1, 3  # fusion candidates: OIDN's estimate, history, rectified history, clipped mean


def trusting(method: Fused, candidate: int = HISTORY) -> Fused:
    """The method with (almost) all its fusion weight on one candidate (the raw history: as a network that lags
    would put it)."""
    sub = method.scale ** 2
    with torch.no_grad():
        method.net.head.bias[candidate * sub:(candidate + 1) * sub] = 12.0
    return method


@torch.no_grad()
def after_a_light_change(scale: int, gain: float, sigmas: float, region: int = 0) -> torch.Tensor:
    """A history-trusting model's last output (at render resolution) when the light holds still for three frames,
    then changes by ``gain``, with the stale-history test at ``sigmas`` and its ``region``."""
    method, state = trusting(build_method("fused", scale)), None
    method.set_stale_test_sigmas(sigmas)
    method.set_stale_region_pixels(region)
    for k in range(4):
        estimate = truth() * (gain if k == 3 else 1.0)
        frame = plane_frame(noisy_constant(estimate, torch.Generator().manual_seed(k)))
        frame.spatial_estimate = estimate
        output, state = method.step(frame, state)
    return torch.nn.functional.avg_pool2d(output, scale) if scale > 1 else output


@pytest.mark.parametrize("scale", [1, 2])
def test_the_stale_history_test_hands_a_changed_light_to_oidn_and_leaves_a_still_one_alone(scale):
    lagging, tested = after_a_light_change(scale, 2.0, 0.0), after_a_light_change(scale, 2.0, 3.0)
    assert float((lagging - truth()).abs().mean()) < 0.05  # without the test the history keeps the old light
    torch.testing.assert_close(tested, truth() * 2.0, atol=0.05, rtol=0.05)  # with it, OIDN's new estimate
    # Unbiased noise alone passes the test (nearly everywhere: 3 standard errors is a test, not a bound).
    torch.testing.assert_close(after_a_light_change(scale, 1.0, 3.0), after_a_light_change(scale, 1.0, 0.0),
                               atol=1e-3, rtol=1e-3)


@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf"), True, "2"])
def test_a_stale_test_threshold_that_is_not_a_finite_number_of_standard_errors_is_refused(value):
    method = build_method("fused")
    with pytest.raises(ValueError, match="finite number of standard errors"):
        method.set_stale_test_sigmas(value)
    assert method.stale_test_sigmas == 0.0


@pytest.mark.parametrize("scale", [1, 2])
def test_the_regional_test_hands_a_small_change_everywhere_to_oidn_where_single_windows_miss_it(scale):
    def error(output: torch.Tensor) -> float:
        return float((output - truth() * 1.25).abs().mean())

    alone, regional = after_a_light_change(scale, 1.25, 3.0), after_a_light_change(scale, 1.25, 3.0, region=15)
    assert error(alone) > 0.8 * error(truth())  # at 3 standard errors the single windows keep most of the old light
    assert error(regional) < 0.4 * error(alone)  # the region sees what few of them do
    torch.testing.assert_close(after_a_light_change(scale, 1.0, 3.0, region=15), after_a_light_change(scale, 1.0, 3.0),
                               atol=2e-3, rtol=2e-3)  # noise alone passes it


@pytest.mark.parametrize("value", [-1, 4, 2.5, True])
def test_a_region_that_is_not_an_odd_whole_number_of_pixels_is_refused(value):
    method = build_method("fused")
    with pytest.raises(ValueError, match="odd whole number of pixels"):
        method.set_stale_region_pixels(value)
    assert method.stale_region_pixels == 0


def test_with_the_stale_history_test_a_zeroed_state_gives_what_no_state_gives():
    # An exported step is fed zeros on an engine's first frame: no valid history, so nothing to distrust.
    method = trusting(build_method("fused"), CLIPPED_MEAN)  # it differs from OIDN's estimate at edges
    method.set_stale_test_sigmas(2.0)
    frame = frame_with_estimate(checker() * 1.7)  # OIDN's estimate far off the noisy frame's mean
    with torch.no_grad():
        fresh, state = method.step(frame, None)
        zeroed, _ = method.step(frame, {name: torch.zeros_like(value) for name, value in state.items()})
    torch.testing.assert_close(zeroed, fresh, atol=1e-5, rtol=1e-5)


def _record_oidn_colours(monkeypatch) -> list[torch.Tensor]:
    """OIDN replaced by the identity: the list fills with the colour it was given, frame by frame."""
    read = []

    def recording_oidn(frame, quality):
        read.append(frame.color.clone())
        return frame.color

    monkeypatch.setattr("model.methods.fused.oidn_denoise", recording_oidn)
    return read


def _checker_frame(sign: float) -> FrameBatch:
    frame = static_frame(size=16)
    pattern = (torch.arange(16).view(1, 16) + torch.arange(16).view(16, 1)) % 2 * 2.0 - 1.0
    return dataclasses.replace(frame, color=(0.5 + 0.4 * sign * pattern).expand(1, 3, 16, 16).clone())


@pytest.mark.parametrize("candidate, count, samples", [
    pytest.param(HISTORY, 2.0, "mean", id="history trusted: the frames add up"),
    pytest.param(0, 0.0, "last", id="OIDN trusted: the mean restarts"),
])
def test_oidn_reads_the_mean_of_the_frames_while_the_network_trusts_its_history(monkeypatch, candidate, count,
                                                                                samples):
    read = _record_oidn_colours(monkeypatch)
    method = trusting(build_method("fused:fast"), candidate)
    method.set_sample_mean_frames(4)
    first, second = _checker_frame(1.0), _checker_frame(-1.0)  # their mean is 0.5 everywhere
    with torch.no_grad():
        _, state = method.step(first, None)
        _, state = method.step(second, state)
    expected = torch.full_like(first.color, 0.5) if samples == "mean" else second.color
    torch.testing.assert_close(read[0], first.color)
    torch.testing.assert_close(read[1], expected)  # both frames' samples, or the new frame's alone
    torch.testing.assert_close(state["samples"][:, :3], expected)
    torch.testing.assert_close(state["samples_count"], torch.full_like(state["samples_count"], count), atol=1e-3,
                               rtol=0)


@pytest.mark.parametrize("power", [2.0, 3.0])
def test_the_sample_mean_keeps_its_frames_in_the_history_share_to_its_trust_power(monkeypatch, power):
    read = _record_oidn_colours(monkeypatch)
    method = build_method("fused:fast")
    with torch.no_grad():  # OIDN's estimate and the history weighed alike: a history share of 1/2
        method.net.head.bias[0] = method.net.head.bias[HISTORY] = 12.0
    method.set_sample_mean_frames(4)
    method.set_sample_mean_trust_power(power)
    first, second = _checker_frame(1.0), _checker_frame(-1.0)
    with torch.no_grad():
        _, state = method.step(first, None)
        method.step(second, state)
    frames = 1 + 0.5 ** power  # the first frame kept in that share, the second added whole
    torch.testing.assert_close(read[1], second.color + (1 - 1 / frames) * (first.color - second.color))


def test_the_sample_mean_trust_power_is_recorded_and_refused_unless_positive():
    saved = build_method("fused:fast")
    assert saved.sample_mean_trust_power == 2.0  # what every model before the setting ran
    saved.set_sample_mean_trust_power(3.0)
    loaded = build_method("fused:fast")
    loaded.load_state_dict(saved.state_dict())
    assert loaded.sample_mean_trust_power == 3.0
    tuned = build_method("fused:fast")
    tuned.load_initial_weights(saved.state_dict())  # a fine-tune (--init-from) runs the power it starts from
    assert tuned.sample_mean_trust_power == 3.0
    loaded.load_state_dict({k: v for k, v in saved.state_dict().items() if k != SAMPLE_MEAN_TRUST_KEY})
    assert loaded.sample_mean_trust_power == 2.0
    for value in (0.0, -1.0, float("inf"), float("nan"), True, "3"):
        with pytest.raises(ValueError, match="finite number > 0"):
            build_method("fused").set_sample_mean_trust_power(value)


def test_the_sample_mean_window_is_recorded_and_refused_when_not_a_whole_number():
    saved = build_method("fused:fast")
    saved.set_sample_mean_frames(8)
    loaded = build_method("fused:fast")
    loaded.load_state_dict(saved.state_dict())
    assert loaded.sample_mean_frames == 8
    tuned = build_method("fused:fast")
    tuned.load_initial_weights(saved.state_dict())  # --init-from keeps it
    assert tuned.sample_mean_frames == 8
    loaded.load_state_dict({k: v for k, v in saved.state_dict().items() if k != SAMPLE_MEAN_KEY})
    assert loaded.sample_mean_frames == 0  # a checkpoint from before it: OIDN reads the single frame
    for value in (-1, 2.5, True):
        with pytest.raises(ValueError, match="whole number of frames >= 0"):
            build_method("fused").set_sample_mean_frames(value)


def test_a_2x_model_steps_with_its_sample_mean_and_keeps_it_at_render_resolution():
    method = trusting(build_method("fused:fast", 2), HISTORY)
    method.set_sample_mean_frames(8)
    with torch.no_grad():
        output, state = method.step(static_frame(size=16, seed=1), None)
        output, state = method.step(static_frame(size=16, seed=1), state)
    assert output.shape[-2:] == (32, 32) and torch.isfinite(output).all()
    assert state["samples"].shape[-2:] == (16, 16) and state["samples_count"].shape == (1, 1, 16, 16)
    assert float(state["samples_count"].median()) > 1.9  # the trusted history's share, pooled to render pixels


def test_a_state_from_before_the_sample_mean_starts_it_at_this_frame():
    older = build_method("fused:fast")
    frame = static_frame(size=16, seed=1)
    with torch.no_grad():
        _, state = older.step(frame, None)
        method = build_method("fused:fast")
        method.set_sample_mean_frames(8)
        output, new_state = method.step(static_frame(size=16, seed=2), state)
    assert torch.isfinite(output).all()
    torch.testing.assert_close(new_state["samples"], frame_samples(static_frame(size=16, seed=2)))


def test_a_state_whose_sample_mean_holds_the_colour_alone_restarts_it_with_the_guides():
    # Sessions stored before the mean averaged the guides hold 3 channels of samples: they start again here.
    method = build_method("fused:fast")
    method.set_sample_mean_frames(8)
    with torch.no_grad():
        _, state = method.step(static_frame(size=16, seed=1), None)
        state["samples"] = state["samples"][:, :3]
        _, new_state = method.step(static_frame(size=16, seed=2), state)
    torch.testing.assert_close(new_state["samples"], frame_samples(static_frame(size=16, seed=2)))
    assert torch.all(new_state["samples_count"] <= 1.0)


def test_oidn_reads_the_guides_averaged_over_the_same_samples_as_the_colour(monkeypatch):
    # A texture finer than a pixel: each jittered frame's albedo sample lands on a light or a dark square, and the
    # colour's mean averages both, so the guide OIDN reads must average them too.
    read = []

    def recording_oidn(frame, quality):
        read.append(frame)
        return frame.color

    monkeypatch.setattr("model.methods.fused.oidn_denoise", recording_oidn)
    method = trusting(build_method("fused:fast"), HISTORY)
    method.set_sample_mean_frames(4)
    first, second = static_frame(size=16, seed=1), static_frame(size=16, seed=1)
    first = dataclasses.replace(first, albedo=torch.full_like(first.albedo, 0.2), specular_albedo=None)
    second = dataclasses.replace(second, albedo=torch.full_like(second.albedo, 0.6), specular_albedo=None)
    with torch.no_grad():
        _, state = method.step(first, None)
        method.step(second, state)
    torch.testing.assert_close(read[1].albedo, torch.full_like(first.albedo, 0.4))
    torch.testing.assert_close(read[1].normal, first.normal)
    assert read[1].specular_albedo is None


@pytest.mark.parametrize("motion, jitter, samples", [
    pytest.param((2.0, 0.0), (0.0, 0.0), "mean", id="whole pixels: the frames add up"),
    pytest.param((0.5, 0.5), (0.0, 0.0), "last", id="half a pixel on both axes, no jitter: the mean restarts"),
    pytest.param((0.5, 0.5), (0.25, -0.25), "third", id="half a pixel, jittered: the mean keeps half a frame"),
])
def test_oidn_reads_the_mean_only_as_far_as_its_warp_keeps_it_sharp(monkeypatch, motion, jitter, samples):
    read = _record_oidn_colours(monkeypatch)
    method = trusting(build_method("fused:fast"), HISTORY)
    method.set_sample_mean_frames(4)
    first, second = _checker_frame(1.0), _checker_frame(-1.0)  # a shift of 2 keeps the checker where it was
    first = dataclasses.replace(first, jitter=torch.tensor([jitter]))
    second = dataclasses.replace(second, motion=torch.tensor(motion).view(1, 2, 1, 1).expand(1, 2, 16, 16).clone(),
                                 jitter=torch.tensor([jitter]))
    with torch.no_grad():
        _, state = method.step(first, None)
        method.step(second, state)
    # at half a pixel both ways the warped checker reads 0.5; jittered, it keeps 1 - 0.5 of its one frame
    expected = {"mean": torch.full_like(first.color, 0.5), "last": second.color,
                "third": second.color * 2 / 3 + 0.5 / 3}[samples]
    inner = (..., slice(1, -3), slice(1, -3))  # the frame's edge reads outside the previous one
    torch.testing.assert_close(read[1][inner], expected[inner])


# ------------------------------------------------------------------------------------ texture detail at 2x

DETAIL_JITTERS = ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25))


def _fine_checker_frame(jitter: tuple[float, float], size: int = 8) -> FrameBatch:
    """A still wall whose albedo is a checker of one target pixel per square at 2x, seen at ``jitter``: the albedo
    guide holds the square each render pixel's sample lies in, the colour the albedo under light 1."""
    checker = 0.3 + 0.4 * ((torch.arange(2 * size).view(-1, 1) + torch.arange(2 * size).view(1, -1)) % 2)
    column, row = (int(2 * (0.5 + value) // 1) for value in jitter)
    albedo = checker.float()[row::2, column::2].expand(1, 3, size, size).contiguous()
    frame = static_frame(size=size, jitter=jitter)
    return dataclasses.replace(frame, albedo=albedo, color=albedo.clone(), spatial_estimate=albedo.clone())


def _stream(method, frames):
    outputs, state = [], None
    with torch.no_grad():
        for frame in frames:
            output, state = method.step(frame, state)
            outputs.append(output)
    return outputs, state


def test_the_texture_detail_is_recorded_and_refused_at_1x_and_when_not_a_whole_number():
    saved = build_method("fused:fast", 2)
    assert saved.albedo_detail_frames == 0
    saved.set_albedo_detail_frames(8)
    loaded = build_method("fused:fast", 2)
    loaded.load_state_dict(saved.state_dict())
    assert loaded.albedo_detail_frames == 8
    tuned = build_method("fused:fast", 2)
    tuned.load_initial_weights(saved.state_dict())  # --init-from keeps it
    assert tuned.albedo_detail_frames == 8
    loaded.load_state_dict({k: v for k, v in saved.state_dict().items() if k != ALBEDO_DETAIL_KEY})
    assert loaded.albedo_detail_frames == 0  # a checkpoint from before it: no detail
    with pytest.raises(ValueError, match="scale 2"):
        build_method("fused:fast", 1).set_albedo_detail_frames(8)
    build_method("fused:fast", 1).set_albedo_detail_frames(0)  # off is off at any scale
    for value in (-1, 2.5, True):
        with pytest.raises(ValueError, match="whole number of frames >= 0"):
            build_method("fused", 2).set_albedo_detail_frames(value)


def test_jittered_frames_give_the_2x_output_the_albedo_texture_and_the_history_stays_the_networks():
    frames = [_fine_checker_frame(jitter, size=16) for jitter in DETAIL_JITTERS]
    plain, plain_state = _stream(build_method("fused:fast", 2), frames)
    method = build_method("fused:fast", 2)
    method.set_albedo_detail_frames(8)
    detailed, state = _stream(method, frames)
    torch.testing.assert_close(state["history"], plain_state["history"])  # the detail never feeds back
    checker = 0.3 + 0.4 * ((torch.arange(32).view(-1, 1) + torch.arange(32).view(1, -1)) % 2).float()
    # Every target pixel holds one sample after the four jitters: the ratio to the render-pixel mean (0.5),
    # trusted 1 / (1 + 2). The geometry test fails on the border, where a jitter's shift reads past the image, and
    # the bicubic mean reads two render pixels on: the pixels further in.
    expected = 1 + ((checker + 0.02) / 0.52 - 1) / 3
    inside = (slice(None), slice(None), slice(6, -6), slice(6, -6))
    torch.testing.assert_close((detailed[-1] / plain[-1])[inside], expected.expand(1, 3, 32, 32)[inside],
                               atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(state["albedo_weight"][inside], torch.ones(1, 1, 20, 20))
    # One frame says nothing of the other sub-pixels: the block of each sample holds its value alone, and the
    # output is the network's.
    torch.testing.assert_close(detailed[0], plain[0])


def test_frames_without_jitter_leave_the_output_as_it_was():
    # A renderer without TAA jitter writes every sample at the pixel centre, a corner of four target pixels.
    frames = [dataclasses.replace(_fine_checker_frame((0.25, 0.25)), jitter=torch.zeros(1, 2)) for _ in range(3)]
    plain, _ = _stream(build_method("fused:fast", 2), frames)
    method = build_method("fused:fast", 2)
    method.set_albedo_detail_frames(8)
    detailed, state = _stream(method, frames)
    for a, b in zip(plain, detailed):
        torch.testing.assert_close(a, b)
    assert float(state["albedo_weight"].sum()) == 0


def test_a_cut_and_a_state_from_before_the_detail_start_the_gather_at_this_frame():
    method = build_method("fused:fast", 2)
    method.set_albedo_detail_frames(8)
    frames = [_fine_checker_frame(jitter) for jitter in DETAIL_JITTERS[:2]]
    _, state = _stream(method, frames)
    assert float(state["albedo_weight"].sum()) > 64  # both frames' samples, but where the border failed the test
    cut = dataclasses.replace(_fine_checker_frame(DETAIL_JITTERS[2]), camera_cut=torch.tensor([True]))
    with torch.no_grad():
        _, after_cut = method.step(cut, state)
        older = {k: v for k, v in state.items() if not k.startswith("albedo_")}
        _, after_old = method.step(_fine_checker_frame(DETAIL_JITTERS[2]), older)
    for new_state in (after_cut, after_old):
        assert float(new_state["albedo_weight"].sum()) == 64  # this frame's samples only


def test_a_2x_model_with_texture_detail_trains_on_a_batch_of_jitters():
    # --init-from keeps the setting, so a fine-tune steps with it: one jitter per item, gradients to the network.
    method = build_method("fused:fast", 2)
    method.set_albedo_detail_frames(8)
    first = [_fine_checker_frame(jitter) for jitter in DETAIL_JITTERS[:2]]
    second = [_fine_checker_frame(jitter) for jitter in DETAIL_JITTERS[2:]]

    def batch(frames):
        return FrameBatch(**{name: torch.cat([getattr(f, name) for f in frames]) for name in frames[0].tensors()})

    _, state = method.step(batch(first), None)
    output, state = method.step(batch(second), state)
    output.mean().backward()
    assert method.net.head.weight.grad is not None and torch.isfinite(method.net.head.weight.grad).all()
    assert state["albedo_weight"].shape == (2, 1, 16, 16)
    # Each item's two jitters filled two sub-pixels of every block, item 0 the left column, item 1 the right.
    blocks = F.avg_pool2d(state["albedo_weight"], 2)[:, :, 2:-2, 2:-2] * 4
    torch.testing.assert_close(blocks, torch.full_like(blocks, 2.0))
    inside = state["albedo_weight"][:, :, 4:-4, 4:-4]
    assert float(inside[0, :, :, 0::2].min()) == 1 and float(inside[1, :, :, 1::2].min()) == 1
