"""model.deployment.compiled_step: a step compiled whole gives the eager step's outputs, and falls back to it when
compiling fails (no C++ compiler, a backend error)."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

import model.deployment.compiled_step as compiled_step
from model.deployment.compiled_step import CompiledStep
from model.deployment.inference_forms import FormTable, form_psnr, run_networks_as, with_inference_forms
from model.io.synthetic import moving_pattern_frames
from model.methods.base import FrameBatch
from model.methods.registry import build_method
from model.ops.graph_breaks import outside_compiled_graph
from model.ops.rectify import clip_to_moments, neighbourhood_moments
from model.ops.reproject import disocclusion_mask
from model.ops.warp import backward_warp

# Inductor reorders and fuses float32 arithmetic (sums, divisions by a product, fused multiply-adds), so a compiled
# op differs from torch's kernels by float32 rounding: a few ulp of values of order 1, never a decision of a test
# (a mask) except on a tie, which seeded random data does not hold.
ATOL, RTOL = 1e-5, 1e-5


def frames(size: int, count: int) -> list[FrameBatch]:
    bundles = moving_pattern_frames(count, (size, size), np.random.default_rng(5))
    return [FrameBatch.from_bundles([bundle], scale=None) for bundle in bundles]


def fused_method():
    torch.manual_seed(0)
    method = build_method("fused:fast", 1).eval().for_inference()
    method.use_shipped_settings()
    with torch.no_grad():  # a network that is not the identity start, so every input reaches the output
        for parameter in method.net.parameters():
            parameter.add_(0.05 * torch.randn_like(parameter))
    return method


def history_ops(image, history, motion, depth, normal, jitter):
    """The reprojection, the history tests and the rectification of a fused step, as one function to compile."""
    warped, inside = backward_warp(torch.cat([history, image], dim=1), motion, mode="bilinear")
    valid = disocclusion_mask(depth, normal, depth * 1.02, normal, motion, jitter=jitter)
    rectified = clip_to_moments(warped[:, :3], *neighbourhood_moments(image))
    return torch.where(valid & inside, rectified, image), valid


def test_compiled_ops_equal_the_eager_ops():
    generator = torch.Generator().manual_seed(1)
    size = (1, 3, 24, 20)
    image, history = torch.rand(size, generator=generator), torch.rand(size, generator=generator)
    motion = 3 * torch.rand((1, 2, 24, 20), generator=generator) - 1.5
    depth = 1 + torch.rand((1, 1, 24, 20), generator=generator)
    normal = torch.nn.functional.normalize(torch.rand(size, generator=generator) - 0.5, dim=1)
    jitter = torch.tensor([[0.25, -0.125]])
    eager = history_ops(image, history, motion, depth, normal, jitter)
    compiled = torch.compile(history_ops, backend=compiled_step.COMPILE_BACKEND)(image, history, motion, depth,
                                                                                  normal, jitter)
    torch.testing.assert_close(compiled[0], eager[0], atol=ATOL, rtol=RTOL)
    assert torch.equal(compiled[1], eager[1])
    assert 0 < int(eager[1].sum()) < eager[1].numel()  # both outcomes of the test occur


def test_a_function_outside_the_graph_runs_eagerly_inside_a_compiled_one():
    seen = []

    @outside_compiled_graph
    def native(x):
        seen.append(torch.compiler.is_compiling())  # a traced call would see True
        return x.numpy().sum()  # numpy: what a native library does with a tensor

    def step(x):
        return (x * 2).sum() + float(native(x + 1))

    x = torch.arange(6.0)
    assert float(torch.compile(step, backend=compiled_step.COMPILE_BACKEND)(x)) == float(step(x)) == 51.0
    assert seen == [False, False]


def test_a_compiled_fused_step_gives_the_eager_steps_outputs():
    method = fused_method()
    batches = frames(24, 3)
    eager_outputs, compiled_outputs, eager_state, compiled_state = [], [], None, None
    with torch.inference_mode():
        for batch in batches:
            output, eager_state = method.step(batch, eager_state)
            eager_outputs.append(output)
            with run_networks_as(method, "compile-step"):
                output, compiled_state = method.step(batch, compiled_state)
            compiled_outputs.append(output)
    assert method._compiled_step.failure is None
    for compiled, eager in zip(compiled_outputs, eager_outputs):
        torch.testing.assert_close(compiled, eager, atol=1e-4, rtol=1e-4)  # a recurrence of three frames
        assert form_psnr(compiled, eager) > 100
    for name in ("history", "mean", "samples", "samples_count", "hidden"):
        torch.testing.assert_close(compiled_state[name], eager_state[name], atol=1e-4, rtol=1e-4)


def failing_backend(graph, example_inputs):
    raise RuntimeError("no C++ compiler on this machine")


def test_a_step_whose_compilation_fails_runs_eagerly_with_the_same_outputs(monkeypatch, caplog):
    monkeypatch.setattr(compiled_step, "COMPILE_BACKEND", failing_backend)
    method = fused_method()
    table = FormTable({"methods": {"fused:fast:x1": {"24x24": {
        "chosen": "compile-step", "ms": {"eager": 2.0, "compile-step": 1.0},
        "psnr_db": {"eager": 200.0, "compile-step": 140.0}}}}})
    reference = fused_method()
    batch = frames(24, 1)[0]
    with torch.inference_mode(), caplog.at_level(logging.WARNING, logger=compiled_step.__name__):
        fast = with_inference_forms(method, table)
        output, _ = fast.step(batch, None)
        again, _ = fast.step(batch, None)  # no second attempt
        expected, _ = reference.step(batch, None)
    assert torch.equal(output, expected) and torch.equal(again, expected)
    assert "no C++ compiler" in method._compiled_step.failure
    assert sum("runs eagerly" in record.getMessage() for record in caplog.records) == 1


def test_no_compiler_on_the_machine_falls_back_to_eager(monkeypatch):
    import torch._inductor.config as inductor_config

    monkeypatch.setattr(inductor_config.cpp, "cxx", ("/nonexistent/c++",))
    monkeypatch.setattr(inductor_config, "fx_graph_cache", False)  # a cached kernel would need no compiler
    monkeypatch.setattr(inductor_config, "autotune_local_cache", False)

    def step(frame, state):
        return frame.exp() * 2 + 1, state

    x = torch.linspace(-1, 1, 64).view(1, 1, 8, 8)
    compiled = CompiledStep(step, backend="inductor")
    output, _ = compiled(x, None)
    assert compiled.failure is not None
    torch.testing.assert_close(output, step(x, None)[0])


def test_an_error_of_the_step_itself_is_raised_and_does_not_disable_compiling():
    def step(frame, state):
        if frame.shape[-1] != 4:
            raise ValueError("frame must be 4 pixels wide")
        return frame + 1, state

    compiled = CompiledStep(step)
    with pytest.raises(ValueError, match="4 pixels wide"):
        compiled(torch.zeros(1, 3), None)
    assert compiled.failure is None
    assert torch.equal(compiled(torch.zeros(1, 4), None)[0], torch.ones(1, 4))


def test_the_table_takes_a_compiled_step_without_allowing_compiled_networks_and_drops_bf16_without_it():
    rows = {"fused:fast:x1": {"512x512": {
        "chosen": "compile-step+bf16",
        "ms": {"eager": 4.0, "compile": 1.0, "compile-step": 2.5, "compile-step+bf16": 2.0},
        "psnr_db": {"eager": 200.0, "compile": 140.0, "compile-step": 140.0, "compile-step+bf16": 85.0}}}}
    table = FormTable({"methods": rows})
    assert not table.allow_compile
    assert table.form_for("fused:fast:x1", 512, 512, bf16=True).name == "compile-step+bf16"
    assert table.form_for("fused:fast:x1", 512, 512, bf16=False).name == "compile-step"
