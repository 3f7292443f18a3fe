"""The native pass between OIDN and the network equals ``Fused._network_inputs`` on seeded states."""

import pytest
import torch
import torch.nn.functional as F

from model.methods.base import FrameBatch
from model.methods.fused import HIDDEN, Fused
from model.ops import native


def _frame(g: torch.Generator, h: int, w: int) -> FrameBatch:
    rand = lambda c: torch.rand(1, c, h, w, generator=g)  # noqa: E731
    return FrameBatch(color=rand(3) * 4, albedo=rand(3), normal=F.normalize(rand(3) - 0.5, dim=1),
                      depth=rand(1) + 0.5, motion=rand(2) - 0.5, jitter=torch.tensor([[0.25, -0.125]]),
                      camera_cut=torch.zeros(1, dtype=torch.bool))


def _state(g: torch.Generator, h: int, w: int, with_mean: bool) -> tuple:
    rand = lambda c: torch.rand(1, c, h, w, generator=g)  # noqa: E731
    valid = rand(1) > 0.4
    count = torch.where(valid, torch.randint(1, 9, (1, 1, h, w), generator=g).float(), torch.ones(1, 1, h, w))
    return (rand(3), rand(HIDDEN) * 2 - 1, rand(1) * 8, valid, rand(3) if with_mean else None,
            count if with_mean else None)


@pytest.mark.parametrize("case", ["first frame", "with mean", "state without mean"])
def test_equals_the_torch_inputs(case):
    g = torch.Generator().manual_seed(7)
    h, w = 37, 53
    method = Fused("balanced", 1)
    frame = _frame(g, h, w)
    s, s_out = torch.rand(1, 3, h, w, generator=g), torch.rand(1, 3, h, w, generator=g)
    state = None if case == "first frame" else {}
    reprojected = None if state is None else _state(g, h, w, case == "with mean")
    with torch.no_grad():
        native.set_enabled(False)
        try:
            expected = method._network_inputs(frame, state, s, s_out, reprojected)
        finally:
            native.set_enabled(True)
        assert native.usable("features", s)
        got = method._network_inputs_native(frame, state, s, s_out, reprojected)
    features, candidates, valid, _, length, mean, count, mean_r = got
    assert features.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(features, expected[0], atol=2e-6, rtol=1e-6)
    for a, b in zip(candidates, expected[1]):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-6)
    assert torch.equal(valid, expected[2])
    for a, b in zip((length, mean, count, mean_r), expected[4:]):
        torch.testing.assert_close(a, b, atol=2e-6, rtol=1e-6)


def test_the_step_takes_the_native_pass_only_where_it_may():
    method = Fused("balanced", 1)
    frame = _frame(torch.Generator().manual_seed(1), 8, 8)
    calls = []
    original = method._network_inputs_native
    method._network_inputs_native = lambda *a: calls.append(1) or original(*a)
    with torch.no_grad():
        method.step(frame, None)
    assert calls == [1]
    with torch.enable_grad():
        method.step(frame, None)  # training: torch ops, gradients
    assert calls == [1]


def test_bfloat16_input_is_the_float32_input_rounded_as_torch_rounds():
    g = torch.Generator().manual_seed(3)
    h, w = 19, 23
    frame = _frame(g, h, w)
    s, s_out = torch.rand(1, 3, h, w, generator=g), torch.rand(1, 3, h, w, generator=g)
    history, hidden, length, valid, mean, count = _state(g, h, w, True)
    from model.ops.native.features import fused_features_x1
    args = (s, s_out, frame.color, frame.albedo, frame.normal, history, valid, length, hidden, mean, count,
            frame.depth, frame.depth.amax(), 8.0, torch.log1p(torch.tensor(16.0)))
    with torch.no_grad():
        full = fused_features_x1(*args)
        half = fused_features_x1(*args, dtype=torch.bfloat16)
    assert half[-1].dtype == torch.bfloat16 and half[-1].is_contiguous(memory_format=torch.channels_last)
    assert torch.equal(half[-1], full[-1].to(torch.bfloat16))
    for a, b in zip(half[:-1], full[:-1]):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="float32 or bfloat16"):
        fused_features_x1(*args, dtype=torch.float16)
