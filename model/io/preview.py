"""A PNG for people to look at: a contact sheet of one frame bundle's buffers side by side, display-encoded.
(An output image, a plain R/G/B EXR, is written as a PNG by ``client.frames.encode_png``.)"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from model.io.frames import FrameBundle  # noqa: E402


def display_encode(image: np.ndarray) -> np.ndarray:
    """The benchmark protocol's display encoding: clip to [0, 1], then gamma 1/2.2."""
    return np.clip(image, 0.0, 1.0) ** (1.0 / 2.2)


def motion_image(motion: np.ndarray) -> np.ndarray:
    """Motion as colour: x in red, y in green, 0.5 = no motion, saturating at the frame's largest motion."""
    largest = max(float(np.abs(motion).max()), 1e-6)
    rgb = np.full(motion.shape[:2] + (3,), 0.5, dtype=np.float32)
    rgb[..., :2] = 0.5 + 0.5 * motion / largest
    return rgb


def buffer_panels(frame: FrameBundle) -> list[tuple[str, np.ndarray]]:
    """(title, displayable image) for every buffer present, in a fixed order."""
    panels = [("color (1spp)", display_encode(frame.color))]
    if frame.diffuse is not None:
        panels += [("diffuse", display_encode(frame.diffuse)), ("specular", display_encode(frame.specular))]
    panels.append(("albedo", np.clip(frame.albedo, 0, 1)))
    if frame.specular_albedo is not None:
        panels.append(("specular albedo", np.clip(frame.specular_albedo, 0, 1)))
    panels.append(("normal", np.clip(frame.normal * 0.5 + 0.5, 0, 1)))
    depth = frame.depth / max(float(frame.depth.max()), 1e-6)
    panels.append(("depth", np.repeat(depth[..., None], 3, axis=2)))
    if frame.roughness is not None:
        panels.append(("roughness", np.repeat(frame.roughness[..., None], 3, axis=2)))
    largest = float(np.abs(frame.motion).max())
    panels.append((f"motion (max {largest:.1f} px)", motion_image(frame.motion)))
    for scale in frame.scales:
        panels.append((f"reference x{scale}", display_encode(frame.reference(scale))))
    return panels


def save_buffer_sheet(frame: FrameBundle, out: str | Path, title: str | None = None) -> Path:
    """Write the contact sheet of `frame` to `out` (PNG) and return the path."""
    panels = buffer_panels(frame)
    columns = min(len(panels), 6)
    rows = -(-len(panels) // columns)
    figure, axes = plt.subplots(rows, columns, figsize=(2.6 * columns, 3.0 * rows), squeeze=False)
    for axis in axes.flat:
        axis.axis("off")
    for axis, (name, image) in zip(axes.flat, panels):
        axis.imshow(image, interpolation="nearest")
        axis.set_title(name, fontsize=9)
    if title:
        figure.suptitle(title, fontsize=10)
    # Room for the suptitle, and for each panel's title below the row above it.
    figure.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.9 if title else 0.95, hspace=0.2, wspace=0.05)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out, dpi=100)
    plt.close(figure)
    return out
