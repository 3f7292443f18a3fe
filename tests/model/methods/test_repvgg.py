"""RepVGG blocks: the fused single convolution computes exactly what the multi-branch training form does."""

import pytest
import torch
from torch import nn

from model.methods.repvgg import RepVGGBlock, reparameterize
from tests.builders import randomize_batch_norms


@pytest.mark.parametrize(
    "in_channels, out_channels, kernel_size, activation",
    [(6, 6, 3, True), (6, 6, 5, True), (4, 7, 3, True), (11, 14, 5, True), (14, 12, 5, False), (5, 5, 1, True)],
)
def test_reparameterized_block_equals_training_form(in_channels, out_channels, kernel_size, activation):
    block = RepVGGBlock(in_channels, out_channels, kernel_size, activation=activation)
    randomize_batch_norms(block)
    block.eval()
    x = torch.randn(2, in_channels, 9, 11)
    with torch.no_grad():
        before = block(x)
        block.reparameterize()
        after = block(x)
    assert block.is_reparameterized
    torch.testing.assert_close(after, before, atol=1e-5, rtol=1e-5)
    if not activation:
        assert (before < 0).any()  # a linear output block keeps negative logits


def test_branches_follow_the_kernel_size_and_identity_only_when_shapes_match():
    block = RepVGGBlock(8, 8, kernel_size=5)
    assert [branch[0].kernel_size for branch in block.branches] == [(5, 5), (3, 3), (1, 1)]
    assert isinstance(block.identity, nn.BatchNorm2d)
    assert RepVGGBlock(8, 4, kernel_size=3).identity is None
    with pytest.raises(ValueError, match="odd"):
        RepVGGBlock(8, 8, kernel_size=4)


def test_fused_block_has_one_convolution_with_bias_and_is_idempotent():
    block = RepVGGBlock(6, 6, kernel_size=3)
    randomize_batch_norms(block)
    block.eval()
    block.reparameterize()
    weights = dict(block.named_parameters())
    assert set(weights) == {"fused.weight", "fused.bias"}
    assert weights["fused.weight"].shape == (6, 6, 3, 3)
    snapshot = {name: p.clone() for name, p in weights.items()}
    block.reparameterize()
    for name, p in block.named_parameters():
        torch.testing.assert_close(p, snapshot[name], rtol=0, atol=0)


def test_module_level_reparameterize_converts_nested_blocks():
    net = nn.Sequential(RepVGGBlock(3, 8, 3), nn.Sequential(RepVGGBlock(8, 8, 5), RepVGGBlock(8, 2, 3, False)))
    randomize_batch_norms(net, seed=3)
    net.eval()
    x = torch.randn(1, 3, 12, 12)
    with torch.no_grad():
        before = net(x)
        assert reparameterize(net) is net
        after = net(x)
    assert all(m.is_reparameterized for m in net.modules() if isinstance(m, RepVGGBlock))
    assert not any(isinstance(m, nn.BatchNorm2d) for m in net.modules())
    torch.testing.assert_close(after, before, atol=1e-5, rtol=1e-5)
