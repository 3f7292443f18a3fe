"""Widening a fused network: the same function before training, wider layers that can learn."""

from __future__ import annotations

import pytest
import torch

from model.training.losses import SequenceLoss
from model.methods.fused import LEGACY_CANDIDATES, Fused
from model.methods.fused_growth import widened_state_dict
from model.methods.registry import build_method, example_batch


def trained_looking(scale: int, legacy: bool = False) -> Fused:
    """A fused model whose every weight is random, the head included (an untrained head is zero, and then the
    network's inside would not show in the output at all)."""
    method = build_method("fused", scale)
    if legacy:  # a checkpoint from before the running mean
        method.net = method._network(LEGACY_CANDIDATES)
    generator = torch.Generator().manual_seed(5)
    with torch.no_grad():
        for parameter in method.net.parameters():
            parameter.copy_(0.2 * torch.randn(parameter.shape, generator=generator))
    return method.eval()


def stream(method: Fused) -> list[torch.Tensor]:
    outputs, state = [], None
    with torch.no_grad():
        for seed in range(3):
            frame = example_batch(24, 24, seed=seed)
            output, state = method.step(frame, state)
            outputs.append(output)
    return outputs


@pytest.mark.parametrize(("scale", "legacy"), [(1, False), (2, False), (1, True)])
def test_a_widened_network_computes_what_it_was_widened_from(scale, legacy):
    source = trained_looking(scale, legacy)
    wide = build_method("fused", scale)
    wide.load_state_dict(widened_state_dict(source.state_dict(), 24, seed=1))
    assert wide.net.width == 24 and wide.net.candidates == source.net.candidates
    assert sum(p.numel() for p in wide.parameters()) > 2 * sum(p.numel() for p in source.parameters())
    for a, b in zip(stream(source), stream(wide.eval()), strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-5)


def test_the_new_channels_learn():
    source = trained_looking(1)
    wide = build_method("fused", 1)
    wide.load_state_dict(widened_state_dict(source.state_dict(), 20, seed=1))
    wide.train()
    frames = [example_batch(24, 24, seed=seed) for seed in range(3)]
    outputs, state = [], None
    for frame in frames:
        output, state = wide.step(frame, state)
        outputs.append(output)
    targets = [torch.rand(output.shape, generator=torch.Generator().manual_seed(9)) for output in outputs]
    SequenceLoss()(outputs, targets).total.backward()
    # The head's columns that read the new channels start at zero; their gradient is what lets them move.
    assert float(wide.net.head.weight.grad[:, 16:].abs().sum()) > 0
    assert float(wide.net.head.weight.detach()[:, 16:].abs().sum()) == 0


@pytest.mark.parametrize("width", [16, 8, 20.0, True])
def test_a_width_that_does_not_widen_is_refused(width):
    with pytest.raises(ValueError, match="more than the model's 16 channels"):
        widened_state_dict(trained_looking(1).state_dict(), width)


def test_a_state_dict_that_is_not_a_fused_network_s_is_refused():
    weights = trained_looking(1).state_dict()
    weights["net.head.weight"] = weights["net.head.weight"][:5]
    with pytest.raises(ValueError, match="not a fused network"):
        widened_state_dict(weights, 24)
