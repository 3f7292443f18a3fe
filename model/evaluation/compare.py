"""A side-by-side picture of one frame: the input upscaled, each method's output, and the reference.

Each method is stepped through the sequence from its first frame up to the chosen one, history carried (as in
evaluation), so the picture shows what the method gives at that point of the stream, not a cold start. Every
panel is titled with its PSNR and FLIP against the reference (display-encoded, as in the benchmark protocol).
An optional zoom row repeats a square region of every panel, enlarged with nearest-neighbour sampling.
``last_frame_panels`` builds the same picture from outputs an evaluation already computed (the evaluate job draws
one per sequence of its last frame this way, without running the methods again).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from model.io.dataset import Sequence
from model.evaluation.evaluate import EvaluationSequence, _prepare
from model.methods.base import FrameBatch, Method
from model.methods.baselines import bicubic_upscale
from model.evaluation.metrics import frame_metrics
from model.ops.tonemap import display_encode


@dataclass
class Panel:
    title: str
    image: np.ndarray  # (H, W, 3) display-encoded, in [0, 1]
    psnr: float | None = None
    flip: float | None = None

    @property
    def caption(self) -> str:
        if self.psnr is None:
            return self.title
        return f"{self.title}\nPSNR {self.psnr:.2f} dB, FLIP {self.flip:.3f}"


def _image(tensor: torch.Tensor) -> np.ndarray:
    return display_encode(tensor[0].float().cpu()).permute(1, 2, 0).numpy()


def _scored(title: str, output: torch.Tensor, reference: torch.Tensor) -> Panel:
    values = frame_metrics(output.float().cpu(), reference)
    return Panel(title, _image(output), float(values["psnr"][0]), float(values["flip"][0]))


def comparison_panels(sequence: Sequence, methods: list[Method | str], frame_index: int, scale: int,
                      labels: list[str | None] | None = None, device: str = "cpu") -> list[Panel]:
    """Input (bicubic-upscaled 1spp colour), one panel per method at ``frame_index``, then the reference."""
    if not 0 <= frame_index < len(sequence):
        raise ValueError(f"frame {frame_index} is outside sequence '{sequence.name}' (frames 0-{len(sequence) - 1})")
    if scale not in sequence.scales:
        present = ", ".join(str(s) for s in sequence.scales) or "none"
        raise ValueError(f"sequence '{sequence.name}' has no references at scale {scale} (scales present: {present})")
    frames = [FrameBatch.from_bundles([sequence[i]], scale) for i in range(frame_index + 1)]
    labels = labels or [None] * len(methods)
    outputs = []
    with torch.inference_mode():
        for method, label in zip(methods, labels, strict=True):
            method, _ = _prepare(method, scale)
            method = method.to(device)
            state = None
            for frame in frames:
                output, state = method.step(frame.without_reference().to(device), state)
            outputs.append((label or method.label, output))
    return _panels(frames[-1], scale, outputs)


def last_frame_panels(sequence: EvaluationSequence, outputs: list[tuple[str, torch.Tensor]]) -> list[Panel]:
    """Input, each (label, output) given for the sequence's last evaluated frame, then the reference."""
    return _panels(sequence.frames[-1], sequence.scale, outputs)


def _panels(frame: FrameBatch, scale: int, outputs: list[tuple[str, torch.Tensor]]) -> list[Panel]:
    reference = frame.reference
    panels = [_scored(f"input (1spp, bicubic x{scale})" if scale > 1 else "input (1spp)",
                      bicubic_upscale(frame.color, scale), reference)]
    panels += [_scored(label, output, reference) for label, output in outputs]
    panels.append(Panel(f"reference x{scale}", _image(reference)))
    return panels


def save_comparison(panels: list[Panel], out: str | Path, title: str | None = None,
                    zoom: tuple[int, int, int] | None = None) -> Path:
    """One row of panels (and a zoom row of the square ``(x, y, size)`` in output pixels); writes a PNG."""
    from matplotlib.figure import Figure

    height, width = panels[0].image.shape[:2]
    if zoom is not None:
        x, y, size = zoom
        if size < 2 or x < 0 or y < 0 or x + size > width or y + size > height:
            raise ValueError(f"zoom square x={x}, y={y}, size={size} does not fit the {width}x{height} output")
    rows = 2 if zoom else 1
    figure = Figure(figsize=(2.8 * len(panels), 3.0 * rows + (0.3 if title else 0)))
    axes = figure.subplots(rows, len(panels), squeeze=False)
    for column, panel in enumerate(panels):
        axis = axes[0][column]
        axis.imshow(np.clip(panel.image, 0, 1), interpolation="nearest")
        axis.set_title(panel.caption, fontsize=8)
        axis.set_axis_off()
        if zoom:
            from matplotlib.patches import Rectangle

            axis.add_patch(Rectangle((x - 0.5, y - 0.5), size, size, fill=False, edgecolor="yellow", linewidth=1))
            crop = panel.image[y:y + size, x:x + size]
            axes[1][column].imshow(np.clip(crop, 0, 1), interpolation="nearest")
            axes[1][column].set_axis_off()
    if title:
        figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=110)
    return out
