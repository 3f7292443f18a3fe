"""OIDN through pyoidn: presets, shapes, noise reduction on a smooth image, the albedo guide, batches."""

from __future__ import annotations

import pyoidn
import pytest
import torch

from model.methods.oidn import OIDN, QUALITIES, oidn_albedo, oidn_device_for
from model.methods.registry import build_method, example_batch, flops_per_pixel, method_spec
from tests.builders import mse, plane_frame

HEIGHT, WIDTH = 16, 16


def smooth_image() -> torch.Tensor:
    """A horizontal ramp from 0.2 to 0.8 times a per-channel tint: smooth, so the denoised answer is known."""
    ramp = torch.linspace(0.2, 0.8, WIDTH).view(1, 1, 1, WIDTH).expand(1, 1, HEIGHT, WIDTH)
    tint = torch.tensor([1.0, 0.8, 0.6]).view(1, 3, 1, 1)
    return (ramp * tint).contiguous()


def test_presets_and_registry():
    spec = method_spec("oidn")
    assert spec.presets == QUALITIES == ("fast", "balanced", "high")
    assert spec.default_preset == "high"
    assert build_method("oidn").preset == "high"
    with pytest.raises(KeyError):
        OIDN("ultra")


@pytest.mark.parametrize("quality", QUALITIES)
def test_each_preset_reduces_error_on_a_noisy_smooth_image(quality):
    truth = smooth_image()
    noisy = truth * 2.0 * torch.rand(truth.shape, generator=torch.Generator().manual_seed(0))
    output, state = build_method(f"oidn:{quality}").step(plane_frame(noisy), None)
    assert output.shape == truth.shape and output.dtype == torch.float32
    assert torch.isfinite(output).all()
    assert state == {}
    assert mse(output, truth) < mse(noisy, truth) / 4


def test_albedo_guide_adds_specular_albedo_and_clips():
    frame = example_batch(HEIGHT, WIDTH)
    frame.albedo = torch.full_like(frame.albedo, 0.7)
    frame.specular_albedo = torch.full_like(frame.albedo, 0.5)
    assert torch.all(oidn_albedo(frame) == 1.0)
    frame.specular_albedo = torch.full_like(frame.albedo, 0.1)
    torch.testing.assert_close(oidn_albedo(frame), torch.full_like(frame.albedo, 0.8))
    frame.specular_albedo = None
    assert oidn_albedo(frame) is frame.albedo


def test_batch_is_denoised_per_sample_and_a_camera_cut_changes_nothing():
    frame = example_batch(HEIGHT, WIDTH, batch=2, seed=1)
    frame.camera_cut = torch.tensor([False, True])
    method = build_method("oidn:fast")
    output, _ = method.step(frame, {})
    without_cut, _ = method.step(example_batch(HEIGHT, WIDTH, batch=2, seed=1), None)
    torch.testing.assert_close(output, without_cut)
    second = example_batch(HEIGHT, WIDTH, batch=2, seed=1)
    alone = type(second)(**{name: value[1:2] for name, value in second.tensors().items()})
    output_alone, _ = method.step(alone, None)
    torch.testing.assert_close(output[1:2], output_alone)


def test_scale_2_returns_twice_the_resolution():
    output, _ = build_method("oidn:fast", scale=2).step(example_batch(HEIGHT, WIDTH, batch=2), None)
    assert output.shape == (2, 3, 2 * HEIGHT, 2 * WIDTH)
    assert torch.isfinite(output).all() and output.min() >= 0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_input_comes_back_on_cuda():
    output, _ = build_method("oidn:fast").step(example_batch(HEIGHT, WIDTH, device="cuda"), None)
    assert output.device.type == "cuda"
    # OIDN's CUDA device (or the CPU fallback) gives what the CPU device gives, to float rounding.
    on_cpu, _ = build_method("oidn:fast").step(example_batch(HEIGHT, WIDTH), None)
    torch.testing.assert_close(output.cpu(), on_cpu, atol=2e-2, rtol=2e-2)


def test_cpu_frames_are_denoised_by_oidns_cpu_device():
    assert oidn_device_for("cpu") == oidn_device_for(torch.device("cpu")) == "cpu"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_a_gpu_frame_uses_oidns_cuda_device_when_this_build_has_one():
    build_method("oidn:fast").step(example_batch(HEIGHT, WIDTH, device="cuda"), None)
    expected = "cuda" if pyoidn.Device.is_cuda_available(0) else "cpu"
    assert oidn_device_for("cuda") == expected


def test_flops_per_pixel_and_parameter_count():
    method = build_method("oidn:fast")
    assert flops_per_pixel(method, HEIGHT, WIDTH) == 0  # not torch ops: the counter sees nothing
    assert method.parameter_count() == 0
