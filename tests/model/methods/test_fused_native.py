"""The fused step with the native passes equals the step with torch's ops, frame by frame over a seeded stream: the
outputs and every state tensor, at 1x, with and without the output kernel (docs/methods.md, "Native kernels")."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model.io.synthetic import moving_pattern_frames
from model.methods.base import FrameBatch
from model.deployment.pretrained import load_pretrained
from model.ops import native
from tests.builders import blurring_oidn, coherent_frame


def _stream(kernel_max_pixels: int, use_native: bool, frames: int = 5) -> list[dict[str, torch.Tensor]]:
    import model.methods.fused as fused
    original, fused.oidn_denoise = fused.oidn_denoise, blurring_oidn
    native.set_enabled(use_native)
    try:
        method = load_pretrained("fused-balanced-x1")  # trained weights: the history and the means carry weight
        method.set_kernel_max_pixels(kernel_max_pixels)
        method.eval().for_inference()
        batches = [coherent_frame(FrameBatch.from_bundles([bundle], scale=None))
                   for bundle in moving_pattern_frames(frames, (40, 28), np.random.default_rng(5))]
        steps, state = [], None
        with torch.no_grad():
            for batch in batches:
                output, state = method.step(batch, state)
                steps.append({"output": output, **state})
        return steps
    finally:
        fused.oidn_denoise = original
        native.set_enabled(True)


@pytest.mark.parametrize("kernel_max_pixels", [0, 100])  # 0: every frame filtered; 100: none (the native tail)
def test_native_step_equals_the_torch_step(kernel_max_pixels):
    native_steps, torch_steps = _stream(kernel_max_pixels, True), _stream(kernel_max_pixels, False)
    for got, expected in zip(native_steps, torch_steps):
        assert got.keys() == expected.keys()
        for key in expected:
            if expected[key].dtype == torch.bool:
                assert torch.equal(got[key], expected[key]), key
            else:
                torch.testing.assert_close(got[key], expected[key], atol=2e-5, rtol=1e-5, msg=key)
    # the history and the means took part: the stream is not the first frame again and again
    assert native_steps[-1]["length"].max() >= 3
    assert native_steps[-1]["samples_count"].max() > 1.0 and native_steps[-1]["count"].max() >= 3


def test_the_native_tail_runs_where_no_output_kernel_does(monkeypatch):
    import model.methods.fused as fused
    calls = []
    original = fused.fused_tail_x1
    monkeypatch.setattr(fused, "fused_tail_x1", lambda *a: calls.append(1) or original(*a))
    _stream(100, True, frames=2)
    assert calls == [1, 1]
    _stream(0, True, frames=2)
    assert calls == [1, 1]
