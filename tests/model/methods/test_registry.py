"""model.methods.registry: one size per model (the size of the form that runs); the buffers each method reads."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from model.methods.registry import (OPTIONAL_RENDER_BUFFERS, MethodSpec, all_methods, build_method, example_batch,
                                    flops_per_pixel, inference_cost, method_buffers, register)


def test_the_cost_of_wskpn_is_its_fused_form_and_the_method_is_left_as_it_was():
    method = build_method("wskpn:xs")
    before = {name: value.clone() for name, value in method.state_dict().items()}
    params, flops = inference_cost(method)
    assert method.training and method.state_dict().keys() == before.keys()
    assert all(torch.equal(value, before[name]) for name, value in method.state_dict().items())
    fused = build_method("wskpn:xs").for_inference()
    assert params == fused.parameter_count() < method.parameter_count()  # RepVGG branches fused away
    assert flops == flops_per_pixel(fused) < flops_per_pixel(method.eval())


def test_methods_without_an_inference_form_cost_what_they_are():
    for name, scale in (("munet:xs", 2), ("svgf", 1)):
        method = build_method(name, scale=scale)
        assert inference_cost(method) == (method.parameter_count(), flops_per_pixel(method))


def _every_method() -> list[tuple[str, int]]:
    return [(f"{spec.name}:{spec.default_preset}", scale) for spec in all_methods() for scale in spec.scales]


@pytest.mark.parametrize("name, scale", _every_method())
def test_a_method_reads_no_optional_buffer_it_does_not_declare(name, scale):
    # Stream clients send only method_buffers; a method reading an undeclared buffer would lose it silently.
    torch.manual_seed(0)
    method = build_method(name, scale=scale).eval()
    reads = set(method_buffers(name.split(":")[0]))
    full = [example_batch(16, 16, seed=seed) for seed in range(3)]
    lean = [dataclasses.replace(frame, **{buffer: None for buffer in OPTIONAL_RENDER_BUFFERS if buffer not in reads})
            for frame in full]
    def outputs(frames):
        state, result = None, []
        with torch.no_grad():
            for frame in frames:
                output, state = method.step(frame, state)
                result.append(output)
        return result

    for got, want in zip(outputs(lean), outputs(full), strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=0)


def test_method_buffers_are_the_required_ones_and_the_declared_optional_ones():
    assert method_buffers("wskpn") == ("color", "albedo", "normal", "depth", "motion")
    assert method_buffers("jnds") == ("color", "albedo", "diffuse", "specular", "normal", "depth", "roughness",
                                      "motion")
    with pytest.raises(KeyError, match="unknown method 'nope'"):
        method_buffers("nope")


def test_a_method_may_declare_only_optional_render_buffers():
    with pytest.raises(ValueError, match="color are not optional render buffers"):
        register(MethodSpec(name="bad", description="", factory=lambda preset, scale: None,
                            optional_buffers=("color",)))


@pytest.mark.parametrize("name, scale", _every_method())
def test_a_step_leaves_the_state_it_is_given_as_it_was(name, scale):
    # A session serializes frame t's history for Redis while frame t + 1 already steps on it (service.sessions.store).
    torch.manual_seed(0)
    method = build_method(name, scale=scale).for_inference()
    frames = [example_batch(16, 16, seed=seed) for seed in range(3)]
    with torch.no_grad():
        _, state = method.step(frames[0], None)
        for frame in frames[1:]:
            before = {key: value.clone() for key, value in state.items()}
            _, new_state = method.step(frame, state)
            assert state.keys() == before.keys()
            for key, value in state.items():
                assert torch.equal(value, before[key]), f"{name} at {scale}x changed state[{key!r}] in place"
            state = new_state


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("name, scale", _every_method())
def test_every_method_streams_on_a_gpu_as_on_the_cpu(name, scale):
    # Sessions and `--device cuda` move the method and the frames; nothing may stay behind on the CPU.
    # cuDNN's TF32 convolutions and OIDN's CUDA device each differ from the CPU by up to about 1e-2.
    torch.manual_seed(0)
    method = build_method(name, scale=scale).eval().for_inference()
    on_gpu = build_method(name, scale=scale).eval().for_inference()
    on_gpu.load_state_dict(method.state_dict())
    on_gpu = on_gpu.to("cuda")
    state_cpu = state_gpu = None
    with torch.no_grad():
        for seed in range(3):
            out_cpu, state_cpu = method.step(example_batch(16, 16, seed=seed), state_cpu)
            out_gpu, state_gpu = on_gpu.step(example_batch(16, 16, seed=seed, device="cuda"), state_gpu)
            assert out_gpu.device.type == "cuda"
            assert all(value.device.type == "cuda" for value in (state_gpu or {}).values()
                       if isinstance(value, torch.Tensor))
            torch.testing.assert_close(out_gpu.cpu(), out_cpu, atol=3e-2, rtol=3e-2)
