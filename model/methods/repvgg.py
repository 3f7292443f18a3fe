"""RepVGG blocks (Ding et al. 2021): several convolution branches for training, one convolution for inference.

Training form of a block with largest kernel ``k`` (odd):

    y = act( sum_{s in k, k-2, ..., 1} BN_s(conv_s x(x))  +  BN_id(x) )

one conv + BatchNorm branch per odd size s <= k (``k=3``: the original RepVGG's 3x3 and 1x1 branches;
``k=5``: WSKPN's variant with 5x5, 3x3 and 1x1, paper section 4.1) and an identity + BatchNorm branch when the
block keeps its channel count. In eval mode every branch is linear (BatchNorm uses its running statistics), so
the sum is one k x k convolution with a bias: :meth:`RepVGGBlock.reparameterize` computes it and replaces the
branches. The extra branches over-parameterize small networks during training (WSKPN reports a PSNR gain for its
6-layer net, paper table 5) at no inference cost.

:func:`reparameterize` converts every block of a module in place; do it after training, before timing or serving.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["RepVGGBlock", "reparameterize"]


def _conv_bn(in_channels: int, out_channels: int, kernel_size: int) -> nn.Sequential:
    # No conv bias: the BatchNorm's shift makes it redundant (and the fused bias comes from BN alone).
    conv = nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2, bias=False)
    return nn.Sequential(conv, nn.BatchNorm2d(out_channels))


def _fold_batch_norm(kernel: torch.Tensor, bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
    """(kernel, bias) of ``bn(conv(x, kernel))`` with BN in eval mode, as one convolution."""
    std = (bn.running_var + bn.eps).sqrt()
    scale = bn.weight / std
    return kernel * scale.view(-1, 1, 1, 1), bn.bias - bn.running_mean * scale


def _pad_to(kernel: torch.Tensor, size: int) -> torch.Tensor:
    """Zero-pad a centred s x s kernel to size x size (same output, since both are 'same'-padded)."""
    pad = (size - kernel.shape[-1]) // 2
    return nn.functional.pad(kernel, (pad, pad, pad, pad))


class RepVGGBlock(nn.Module):
    """Conv block with parallel k x k, ..., 3x3, 1x1 (+ identity) branches; ``reparameterize`` fuses them.

    ``activation=False`` leaves the sum linear (for output layers whose values are logits).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, activation: bool = True):
        super().__init__()
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be a positive odd integer, got {kernel_size}")
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.kernel_size = kernel_size
        self.branches = nn.ModuleList(
            _conv_bn(in_channels, out_channels, size) for size in range(kernel_size, 0, -2)
        )
        self.identity = nn.BatchNorm2d(in_channels) if in_channels == out_channels else None
        self.activation = nn.ReLU(inplace=True) if activation else nn.Identity()
        self.fused: nn.Conv2d | None = None

    @property
    def is_reparameterized(self) -> bool:
        return self.fused is not None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.fused is not None:
            return self.activation(self.fused(x))
        out = self.branches[0](x)
        for branch in self.branches[1:]:
            out = out + branch(x)
        if self.identity is not None:
            out = out + self.identity(x)
        return self.activation(out)

    def fused_kernel_and_bias(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The single k x k convolution (weight, bias) equal to the branches' sum with BatchNorm in eval mode."""
        if self.fused is not None:
            return self.fused.weight, self.fused.bias
        k = self.kernel_size
        weight = torch.zeros_like(self.branches[0][0].weight)
        bias = torch.zeros_like(self.branches[0][1].bias)
        for branch in self.branches:
            kernel, shift = _fold_batch_norm(branch[0].weight, branch[1])
            weight = weight + _pad_to(kernel, k)
            bias = bias + shift
        if self.identity is not None:
            # Identity = a convolution whose kernel is 1 at the centre tap of channel i -> i.
            eye = torch.zeros_like(weight)
            centre = k // 2
            channels = torch.arange(self.in_channels, device=weight.device)
            eye[channels, channels, centre, centre] = 1.0
            kernel, shift = _fold_batch_norm(eye, self.identity)
            weight = weight + kernel
            bias = bias + shift
        return weight, bias

    @torch.no_grad()
    def reparameterize(self) -> None:
        """Replace the branches by their fused convolution (in place; idempotent)."""
        if self.fused is not None:
            return
        weight, bias = self.fused_kernel_and_bias()
        fused = nn.Conv2d(self.in_channels, self.out_channels, self.kernel_size, padding=self.kernel_size // 2)
        fused = fused.to(device=weight.device, dtype=weight.dtype)
        fused.weight.copy_(weight)
        fused.bias.copy_(bias)
        self.fused = fused
        # The branches' parameters are now inside `fused`; dropping them keeps parameters() and state_dict()
        # to what inference uses.
        self.branches = nn.ModuleList()
        self.identity = None

    def extra_repr(self) -> str:
        form = "fused" if self.is_reparameterized else "multi-branch"
        return f"{self.in_channels}, {self.out_channels}, kernel_size={self.kernel_size}, {form}"


def reparameterize(module: nn.Module) -> nn.Module:
    """Fuse every RepVGGBlock inside ``module`` (in place) and return ``module``."""
    for child in module.modules():
        if isinstance(child, RepVGGBlock):
            child.reparameterize()
    return module
