"""A shared check that a learned method can fit one fixed noisy/clean pair (its gradients are useful)."""

from __future__ import annotations

import torch

from model.methods.base import FrameBatch, Method


def overfit_l1(method: Method, frame: FrameBatch, clean: torch.Tensor, steps: int = 60,
               lr: float = 3e-3) -> tuple[float, float]:
    """L1 of the first-frame output against `clean` before and after `steps` Adam steps on that one frame."""
    method.train()
    optimizer = torch.optim.Adam(method.parameters(), lr=lr)

    def l1() -> torch.Tensor:
        output, _ = method.step(frame, None)
        return (output - clean).abs().mean()

    with torch.no_grad():
        initial = l1().item()
    for _ in range(steps):
        optimizer.zero_grad()
        l1().backward()
        optimizer.step()
    with torch.no_grad():
        final = l1().item()
    return initial, final
