"""The output bound: no method's step returns radiance above its frame's input allowance, or a non-finite value.

Every registered method at every scale, untrained and with extreme weights, is driven through adversarial tiny
sequences (a moving visible emitter, fireflies, an emitter that appears and vanishes, a history far brighter than
the frames after it); every shipped model too.
"""

from __future__ import annotations

import math

import pytest
import torch

from model.methods.base import FrameBatch, unbounded_step
from model.methods.registry import all_methods, build_method
from model.ops.output_bound import (OUTPUT_BOUND_FACTOR, OUTPUT_BOUND_FLOOR, bound_output, output_bound,
                                    output_ratio)

SIZE = 16
FRAMES = 5
LAMP = 300.0


def _frame(color: torch.Tensor, seed: int, motion: tuple[float, float] = (0.0, 0.0)) -> FrameBatch:
    generator = torch.Generator().manual_seed(seed)
    albedo = 0.2 + 0.6 * torch.rand(1, 3, SIZE, SIZE, generator=generator)
    normal = torch.nn.functional.normalize(torch.rand(1, 3, SIZE, SIZE, generator=generator) * 2 - 1, dim=1)
    depth = 1.0 + torch.rand(1, 1, SIZE, SIZE, generator=generator)
    move = torch.tensor(motion, dtype=torch.float32).view(1, 2, 1, 1).expand(1, 2, SIZE, SIZE).contiguous()
    diffuse = color * 0.7
    return FrameBatch(color=color, albedo=albedo, normal=normal, depth=depth, motion=move,
                      jitter=torch.zeros(1, 2), camera_cut=torch.zeros(1, dtype=torch.bool), diffuse=diffuse,
                      specular=color - diffuse, specular_albedo=torch.full((1, 3, SIZE, SIZE), 0.04),
                      roughness=torch.full((1, 1, SIZE, SIZE), 0.3))


def _noise(seed: int, level: float = 0.5) -> torch.Tensor:
    return level * torch.rand(1, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(seed))


def moving_emitter() -> list[FrameBatch]:
    """A 2x2 lamp crossing the frame 3 pixels a frame; the motion vectors point back to where it was."""
    frames = []
    for t in range(FRAMES):
        color = _noise(t)
        color[:, :, 6:8, 2 + 3 * t:4 + 3 * t] = LAMP
        frames.append(_frame(color, t, motion=(-3.0, 0.0)))
    return frames


def fireflies() -> list[FrameBatch]:
    """Dim frames with a few isolated samples 10^4 times brighter, new positions every frame."""
    frames = []
    for t in range(FRAMES):
        color = _noise(10 + t, 0.05)
        where = torch.randperm(SIZE * SIZE, generator=torch.Generator().manual_seed(t))[:3]
        color.view(1, 3, -1)[:, :, where] = 500.0
        frames.append(_frame(color, 10 + t))
    return frames


def emitter_appears_and_vanishes() -> list[FrameBatch]:
    """A lamp only on the middle frames; the frames around it are plain noise."""
    frames = []
    for t in range(FRAMES):
        color = _noise(20 + t)
        if t in (1, 2):
            color[:, :, 4:9, 4:9] = LAMP
        frames.append(_frame(color, 20 + t))
    return frames


def bright_history_then_dark() -> list[FrameBatch]:
    """Two frames at the top of the range (10^4 everywhere), then near-black frames: the history is at its edge."""
    return [_frame(torch.full((1, 3, SIZE, SIZE), 1e4) if t < 2 else _noise(30 + t, 1e-3), 30 + t)
            for t in range(FRAMES)]


SEQUENCES = {"moving_emitter": moving_emitter, "fireflies": fireflies,
             "emitter_appears_and_vanishes": emitter_appears_and_vanishes,
             "bright_history_then_dark": bright_history_then_dark}
METHODS = [(spec.name, scale) for spec in all_methods() for scale in spec.scales]


def _assert_bounded(method, frames: list[FrameBatch], where: str) -> None:
    state = None
    with torch.no_grad():
        for index, frame in enumerate(frames):
            output, state = method.step(frame, state)
            assert bool(torch.isfinite(output).all()), f"{where}, frame {index}: non-finite output"
            assert float(output.min()) >= 0.0, f"{where}, frame {index}: negative output"
            ratio = output_ratio(output, frame.color)
            assert ratio <= OUTPUT_BOUND_FACTOR * (1 + 1e-6), f"{where}, frame {index}: output / input {ratio:.3g}"


def _extreme(method) -> None:
    """Every parameter replaced by large seeded noise: the network outputs whatever it outputs."""
    generator = torch.Generator().manual_seed(7)
    with torch.no_grad():
        for parameter in method.parameters():
            if parameter.is_floating_point():
                parameter.copy_(50.0 * torch.randn(parameter.shape, generator=generator))


def test_bound_output_clamps_to_the_frames_peak_and_replaces_nan():
    color = torch.tensor([0.5, 2.0, math.inf, math.nan]).view(1, 1, 2, 2)
    assert float(output_bound(color)) == pytest.approx(2.0 * OUTPUT_BOUND_FACTOR)  # non-finite input ignored
    output = torch.tensor([1.0, 1e6, -3.0, math.nan, math.inf, 0.25]).view(1, 1, 2, 3)
    bounded = bound_output(output, color)
    assert bounded.flatten().tolist() == pytest.approx([1.0, 2.0 * OUTPUT_BOUND_FACTOR, 0.0, 0.0,
                                                        2.0 * OUTPUT_BOUND_FACTOR, 0.25])
    dark = torch.full((1, 3, 2, 2), 1e-3)  # a near-black frame keeps headroom up to the floor
    assert float(output_bound(dark)) == pytest.approx(OUTPUT_BOUND_FLOOR * OUTPUT_BOUND_FACTOR)


def test_the_bound_is_per_sample():
    color = torch.stack([torch.full((3, 2, 2), 4.0), torch.full((3, 2, 2), 100.0)])
    bounded = bound_output(torch.full((2, 3, 4, 4), 1e3), color)  # a 2x output against 1x inputs
    assert bounded[0].max() == pytest.approx(4.0 * OUTPUT_BOUND_FACTOR)
    assert bounded[1].max() == pytest.approx(100.0 * OUTPUT_BOUND_FACTOR)


@pytest.mark.parametrize("name,scale", METHODS)
def test_every_method_is_bounded_on_adversarial_frames(name, scale):
    torch.manual_seed(0)
    method = build_method(name, scale).eval()
    for sequence, make in SEQUENCES.items():
        _assert_bounded(method, make(), f"{name} x{scale} on {sequence}")


@pytest.mark.parametrize("name,scale", [(n, s) for n, s in METHODS if build_method(n, s).learned])
def test_learned_methods_with_extreme_weights_are_bounded(name, scale):
    torch.manual_seed(0)
    method = build_method(name, scale).eval()
    _extreme(method)
    frames = moving_emitter()
    with torch.no_grad():  # without the bound the network's output is far out of range: the test can fail
        unbounded, state = [], None
        for frame in frames:
            output, state = unbounded_step(method, frame, state)
            unbounded.append(output_ratio(output, frame.color))
    assert max(unbounded) > OUTPUT_BOUND_FACTOR
    _assert_bounded(method, frames, f"{name} x{scale} with extreme weights")


def test_every_shipped_model_is_bounded_on_adversarial_frames():
    from model.deployment.pretrained import load_pretrained, pretrained_names

    for name in pretrained_names():
        method = load_pretrained(name)
        for sequence, make in SEQUENCES.items():
            _assert_bounded(method, make(), f"{name} on {sequence}")
