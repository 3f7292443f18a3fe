"""OIDN + TAA: the recipe step by step on frames with known answers."""

from __future__ import annotations

import pytest
import torch

from model.methods.oidn import oidn_denoise
from model.methods.oidn_taa import OIDNTAA, reinhard, reinhard_inverse
from model.methods.registry import build_method, method_spec
from tests.builders import mse, noisy_constant, plane_frame

SIZE = 24


def truth() -> torch.Tensor:
    ramp = torch.linspace(0.2, 0.8, SIZE).view(1, 1, 1, SIZE).expand(1, 1, SIZE, SIZE)
    return (ramp * torch.tensor([1.0, 0.8, 0.6]).view(1, 3, 1, 1)).contiguous()


def test_registered_with_oidn_qualities_at_both_scales():
    spec = method_spec("oidn-taa")
    assert spec.presets == ("fast", "balanced", "high") and spec.default_preset == "high"
    assert spec.scales == (1, 2) and not spec.learned
    assert build_method("oidn-taa:fast", 2).step(plane_frame(truth()), None)[0].shape == (1, 3, 2 * SIZE, 2 * SIZE)
    with pytest.raises(KeyError, match="presets"):
        OIDNTAA("ultra")


def test_first_frame_is_oidn_and_later_frames_blend_the_clipped_history():
    generator = torch.Generator().manual_seed(0)
    frames = [plane_frame(noisy_constant(truth(), generator)) for _ in range(3)]
    method = build_method("oidn-taa:fast")
    first, state = method.step(frames[0], None)
    torch.testing.assert_close(first, reinhard_inverse(reinhard(oidn_denoise(frames[0], "fast"))))
    second, _ = method.step(frames[1], state)
    # Static scene, zero motion: history = first output; the recipe's blend on the tone-mapped values.
    from model.ops.rectify import variance_clip
    current = reinhard(oidn_denoise(frames[1], "fast"))
    expected = 0.2 * current + 0.8 * variance_clip(reinhard(first), current)
    torch.testing.assert_close(second, reinhard_inverse(expected), atol=1e-5, rtol=1e-5)


def test_on_a_static_scene_it_beats_oidn_alone():
    generator = torch.Generator().manual_seed(1)
    frames = [plane_frame(noisy_constant(truth(), generator)) for _ in range(8)]
    method, state = build_method("oidn-taa:fast"), None
    for frame in frames:
        output, state = method.step(frame, state)
    assert mse(output, truth()) < mse(oidn_denoise(frames[-1], "fast"), truth())


def test_history_is_dropped_where_depth_fails_and_after_a_cut():
    generator = torch.Generator().manual_seed(2)
    method = build_method("oidn-taa:fast")
    _, state = method.step(plane_frame(noisy_constant(truth(), generator)), None)
    moved = plane_frame(noisy_constant(truth(), generator), depth=torch.full((1, 1, SIZE, SIZE), 3.0))
    output, _ = method.step(moved, state)
    torch.testing.assert_close(output, reinhard_inverse(reinhard(oidn_denoise(moved, "fast"))))
    cut = plane_frame(noisy_constant(truth(), generator), camera_cut=[True])
    output, _ = method.step(cut, state)
    torch.testing.assert_close(output, reinhard_inverse(reinhard(oidn_denoise(cut, "fast"))))


def test_a_stale_bright_history_is_clipped_not_smeared():
    method = build_method("oidn-taa:fast")
    bright = plane_frame(torch.full((1, 3, SIZE, SIZE), 20.0))
    _, state = method.step(bright, None)  # the light was here
    dark = plane_frame(torch.full((1, 3, SIZE, SIZE), 0.1))
    output, _ = method.step(dark, state)  # and is gone: a flat dark neighbourhood clips the history to itself
    assert float(output.max()) < 0.2
