"""AFN: shapes and finiteness per preset, temporal accumulation and camera cuts, the scale compositor's closed
form, gradients through unrolled steps, and a short overfit."""


import pytest
import torch

from model.methods.afn import AFN, AFN_PRESETS, scale_composite
from model.ops.demodulate import demodulate
from model.methods.registry import build_method, example_batch, flops_per_pixel, method_spec
from tests.builders import sample, static_frame
from tests.model.methods.overfitting import overfit_l1


def test_registry_entry():
    spec = method_spec("afn")
    assert spec.learned and spec.scales == (1, 2)
    assert spec.presets == ("xs", "s", "m", "l") and spec.default_preset == "m"
    method = build_method("afn")
    assert isinstance(method, AFN) and method.preset == "m" and method.kernel_size == 7  # the paper's k


@pytest.mark.parametrize("preset", list(AFN_PRESETS))
def test_every_preset_gives_finite_output_with_and_without_history(preset):
    method = build_method(f"afn:{preset}")
    frame = example_batch(16, 16)
    with torch.no_grad():
        first, state = method.step(frame, None)
        second, state = method.step(example_batch(16, 16, seed=1), state)
    for output in (first, second):
        assert output.shape == (1, 3, 16, 16)
        assert torch.isfinite(output).all() and (output >= 0).all()
    assert set(state) == {"accumulated", "count", "depth", "normal", "jitter"}


def test_presets_grow_in_size_and_cost():
    methods = [build_method(f"afn:{p}") for p in AFN_PRESETS]
    params = [m.parameter_count() for m in methods]
    flops = [flops_per_pixel(m, 16, 16) for m in methods]
    assert params == sorted(params) and len(set(params)) == len(params)
    assert flops == sorted(flops) and flops[0] > 0


def test_odd_size_runs():
    method = build_method("afn:xs")
    with torch.no_grad():
        output, _ = method.step(example_batch(15, 13), None)
    assert output.shape == (1, 3, 15, 13) and torch.isfinite(output).all()


def test_scale_2_denoises_then_upscales():
    method = build_method("afn:xs", scale=2)
    with torch.no_grad():
        output, state = method.step(example_batch(16, 16, batch=2), None)
        output, _ = method.step(example_batch(16, 16, batch=2, seed=1), state)
    assert output.shape == (2, 3, 32, 32) and torch.isfinite(output).all() and (output >= 0).all()
    assert state["accumulated"].shape == (2, 3, 16, 16)  # history stays at render resolution


def test_temporal_accumulation_averages_a_static_scene():
    method = build_method("afn:xs")
    frames = [static_frame(seed=s) for s in range(3)]
    state = None
    with torch.no_grad():
        for frame in frames:
            _, state = method.step(frame, state)
    radiance = torch.stack([demodulate(f.color, f.albedo)[0] for f in frames])
    assert torch.equal(state["count"], torch.full_like(state["count"], 3.0))
    torch.testing.assert_close(state["accumulated"], radiance.mean(dim=0))  # exact running mean below 1/alpha_min


def test_failed_geometry_test_restarts_accumulation():
    method = build_method("afn:xs")
    first, moved = static_frame(seed=0), static_frame(seed=1)
    moved.depth = moved.depth * 2  # a different surface: the depth test fails everywhere
    with torch.no_grad():
        _, state = method.step(first, None)
        _, state = method.step(moved, state)
    assert torch.equal(state["count"], torch.ones_like(state["count"]))
    torch.testing.assert_close(state["accumulated"], demodulate(moved.color, moved.albedo)[0])


def test_camera_cut_resets_only_that_sample():
    method = build_method("afn:s")
    first, second = static_frame(2, seed=0), static_frame(2, seed=1, cut=[True, False])
    with torch.no_grad():
        _, state = method.step(first, None)
        output, state = method.step(second, state)
        # Reference runs, one sample at a time: sample 0 as a fresh sequence, sample 1 continuing its history.
        fresh_0, _ = method.step(sample(second, 0), None)
        _, state_1 = method.step(sample(first, 1), None)
        continued_1, _ = method.step(sample(second, 1), state_1)
        fresh_1, _ = method.step(sample(second, 1), None)
    torch.testing.assert_close(output[0:1], fresh_0)
    torch.testing.assert_close(output[1:2], continued_1)
    assert not torch.allclose(continued_1, fresh_1, atol=1e-4)  # history matters, so the check above has teeth
    assert torch.equal(state["count"][0], torch.ones_like(state["count"][0]))
    assert torch.equal(state["count"][1], torch.full_like(state["count"][1], 2.0))


@pytest.mark.parametrize("preset", list(AFN_PRESETS))
def test_gradients_reach_every_parameter_through_two_steps(preset):
    method = build_method(f"afn:{preset}")
    state = None
    loss = torch.zeros(())
    for seed in range(2):
        output, state = method.step(static_frame(seed=seed), state)
        loss = loss + output.mean()
    loss.backward()
    for name, parameter in method.named_parameters():
        assert parameter.grad is not None, name
        assert torch.isfinite(parameter.grad).all(), name
        assert parameter.grad.abs().sum() > 0, name


def test_scale_composite_closed_form():
    # fine 2x4: two 2x2 blocks with means 2.5 and 10; coarse 1x2.
    fine = torch.tensor([[1.0, 2.0, 8.0, 12.0], [3.0, 4.0, 10.0, 10.0]]).view(1, 1, 2, 4)
    coarse = torch.tensor([[7.0, -1.0]]).view(1, 1, 1, 2)
    block_mean = torch.tensor([[2.5, 2.5, 10.0, 10.0]] * 2).view(1, 1, 2, 4)
    coarse_up = torch.tensor([[7.0, 7.0, -1.0, -1.0]] * 2).view(1, 1, 2, 4)

    zero, one = torch.zeros(1, 1, 2, 4), torch.ones(1, 1, 2, 4)
    torch.testing.assert_close(scale_composite(fine, coarse, zero), fine)
    torch.testing.assert_close(scale_composite(fine, coarse, one), fine - block_mean + coarse_up)
    # a = 1 keeps the detail within each block and takes the block means from the coarse image.
    torch.testing.assert_close(torch.nn.functional.avg_pool2d(scale_composite(fine, coarse, one), 2), coarse)
    # Per-pixel alpha, one value per column: fine + a * (U(coarse) - U(D(fine))).
    alpha = torch.tensor([0.0, 0.5, 0.25, 1.0]).view(1, 1, 1, 4).expand(1, 1, 2, 4)
    torch.testing.assert_close(scale_composite(fine, coarse, alpha), fine + alpha * (coarse_up - block_mean))


def test_scale_composite_odd_size_and_shape_check():
    fine = torch.arange(9.0).view(1, 1, 3, 3)
    coarse = torch.zeros(1, 1, 2, 2)
    # a = 1, coarse 0: subtracts the block means; the last row/column's "block" is the replicated border.
    expected = fine - torch.tensor([[2.0, 2.0, 3.5], [2.0, 2.0, 3.5], [6.5, 6.5, 8.0]]).view(1, 1, 3, 3)
    torch.testing.assert_close(scale_composite(fine, coarse, torch.ones(1, 1, 3, 3)), expected)
    with pytest.raises(ValueError, match="coarse"):
        scale_composite(fine, torch.zeros(1, 1, 3, 3), torch.ones(1, 1, 3, 3))


def test_demodulation_round_trips_and_leaves_no_albedo_pixels_alone():
    color = torch.rand(1, 3, 4, 4) * 3
    albedo = torch.rand(1, 3, 4, 4)
    albedo[..., 0, 0] = 0.0  # a sky pixel
    radiance, divisor = demodulate(color, albedo)
    torch.testing.assert_close(radiance * divisor, color)
    torch.testing.assert_close(radiance[..., 0, 0], color[..., 0, 0])


def test_overfits_one_pair():
    """60 Adam steps on one fixed noisy/clean 16x16 pair must cut the L1 error by at least 30%."""
    g = torch.Generator().manual_seed(0)
    ys, xs = torch.meshgrid(torch.linspace(0, 1, 16), torch.linspace(0, 1, 16), indexing="ij")
    clean = torch.stack([0.2 + 0.6 * xs, 0.3 + 0.4 * ys, 0.5 + 0.3 * xs * ys]).unsqueeze(0)
    noise = -torch.log(torch.rand(1, 3, 16, 16, generator=g).clamp_min(1e-6))  # Exp(1): mean 1, heavy tail
    frame = static_frame(seed=0)
    frame.color = clean * noise
    method = build_method("afn:xs")
    initial, final = overfit_l1(method, frame, clean, lr=3e-3)
    assert final <= 0.7 * initial, (initial, final)
