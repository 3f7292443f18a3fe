"""A tiny learned method and a tiny synthetic dataset for the training-engine tests (no Mitsuba).

Importing this module registers the method as ``tiny_test`` (presets ``default`` and ``dropout``); DDP rank
processes import it by name (``workers.ddp.launch(..., imports=[__name__])``) to find it in their registry.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from model.dataset import Dataset, SequenceWriter
from model.frames import FrameBundle, box_downsample
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


def synthetic_frame(rng: np.random.Generator, index: int, width: int, height: int, camera_cut: bool = False,
                    scales: tuple[int, ...] = (1, 2)) -> FrameBundle:
    """A valid random frame: a smooth reference, noisy color around it, random geometry and a small motion."""
    top = max(scales)
    ys, xs = np.mgrid[0:height * top, 0:width * top].astype(np.float32) / top
    phase = rng.uniform(0, 6, size=3).astype(np.float32)
    reference_top = np.stack([0.5 + 0.4 * np.sin(0.3 * xs + 0.2 * ys + p) for p in phase], axis=2)
    references = {top: reference_top.astype(np.float32)}
    for scale in scales:
        references[scale] = box_downsample(reference_top, top // scale) if scale != top else references[top]
    noise = rng.exponential(1.0, size=(height, width, 3)).astype(np.float32)
    color = references[1] * noise if 1 in references else box_downsample(reference_top, top) * noise
    normal = rng.normal(size=(height, width, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    diffuse = (color * rng.uniform(0.2, 0.8, size=color.shape)).astype(np.float32)
    return FrameBundle(
        color=color, albedo=rng.uniform(0, 1, size=(height, width, 3)).astype(np.float32), normal=normal,
        depth=rng.uniform(1, 5, size=(height, width)).astype(np.float32),
        motion=rng.uniform(-1, 1, size=(height, width, 2)).astype(np.float32),
        jitter=tuple(float(v) for v in rng.uniform(-0.5, 0.5, size=2)), frame_index=index, camera_cut=camera_cut,
        diffuse=diffuse, specular=color - diffuse,
        references={scale: references[scale] for scale in scales})


def write_sequence(root: Path, name: str, frames: int, size: tuple[int, int] = (16, 16), cuts: tuple[int, ...] = (),
                   seed: int = 0, scales: tuple[int, ...] = (1, 2)) -> Path:
    rng = np.random.default_rng(seed)
    width, height = size
    with SequenceWriter(root / name, name) as writer:
        for index in range(frames):
            writer.add(synthetic_frame(rng, index, width, height, camera_cut=index in cuts, scales=scales))
    return root / name


def write_tiny_dataset(root: Path, size: tuple[int, int] = (16, 16)) -> Path:
    """Two training sequences (one with a cut at frame 3) and one validation sequence, 16x16 by default."""
    dataset = Dataset.create(root)
    for name, split, frames, cuts, seed in (("alpha", "train", 6, (3,), 1), ("beta", "train", 5, (), 2),
                                            ("gamma", "validation", 3, (), 3)):
        write_sequence(root, name, frames, size, cuts, seed)
        dataset.add_sequence_dir(name, split)
    return root
