"""A tiny learned method for the training-engine tests (no Mitsuba); its data: ``tests.builders.write_tiny_dataset``.

Importing this module registers the method as ``tiny_test`` (presets ``default`` and ``dropout``); DDP rank
processes import it by name (``workers.ddp.launch(..., imports=[__name__])``) to find it in their registry.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from model.methods.base import FrameBatch, Method, State, drop_history
from model.methods.registry import MethodSpec, register
from model.ops.warp import backward_warp

TINY_METHOD = "tiny_test"


class TinyMethod(Method):
    """Two 3x3 convolutions predict a denoised frame and a blend weight with the warped previous output."""

    name = TINY_METHOD
    learned = True

    def __init__(self, preset: str = "default", scale: int = 1) -> None:
        super().__init__(preset, scale)
        self.features = nn.Conv2d(3 + 3 + 3 + 1 + 3, 8, 3, padding=1)
        self.head = nn.Conv2d(8, 4, 3, padding=1)
        # The dropout preset makes training consume the global RNG, which exact resume must restore.
        self.dropout = nn.Dropout2d(0.25) if preset == "dropout" else nn.Identity()

    def step(self, frame: FrameBatch, state: State | None) -> tuple[torch.Tensor, State]:
        state = drop_history(state, frame)
        color = torch.log1p(frame.color)
        if state is None:
            history, has_history = color, torch.zeros_like(frame.depth)
        else:
            history, _ = backward_warp(state["output"], frame.motion, jitter=frame.jitter)
            history, has_history = torch.log1p(history.clamp_min(0)), state["valid"]
        inputs = torch.cat([color, frame.albedo, frame.normal, frame.depth / (1 + frame.depth), history], dim=1)
        predicted = self.head(self.dropout(F.relu(self.features(inputs))))
        blend = torch.sigmoid(predicted[:, :1]) * has_history  # weight of the history
        denoised = color + predicted[:, 1:]
        output = torch.expm1((1 - blend) * denoised + blend * history).clamp_min(0)
        return output, {"output": output, "valid": torch.ones_like(frame.depth)}


register(MethodSpec(name=TINY_METHOD, description="test-only 2-layer conv net with a temporal blend",
                    factory=TinyMethod, presets=("default", "dropout"), learned=True))

