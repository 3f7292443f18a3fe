"""Ghosting: where a light or an object was a few frames ago, does a method's output still show it?

Temporal methods reuse history; where the scene changed, history that was not rejected leaves a trail (a bright
smear behind a moving visible lamp, a translucent copy of an object over the wall it slid across). The measure needs
no hand-made masks: the *trail region* comes from the references and motion vectors alone (``trail_masks``), and a
method's ghosting is its error against the reference inside that region (``ghosting_error``), both on display-encoded
images as PSNR is. A pixel *changed* where the 3x3 mean of frame t's reference differs by more than
``CHANGE_THRESHOLD`` from that of frame t-1's reference warped to frame t (the means keep the references' own noise
and resampled sub-pixel detail out); the trail is what changed in the last ``TRAIL_FRAMES`` frames, carried along the
motion. Frame 0 and a frame after a camera cut have no trail. The measure in detail: docs/stability.md, "Ghosting".
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from model.evaluation.metrics import PSNR_CAP_DB
from model.ops.tonemap import display_encode
from model.ops.warp import backward_warp, upscale_motion

__all__ = ["TRAIL_FRAMES", "CHANGE_THRESHOLD", "GHOSTING_DEFINITION", "changed_regions", "trail_masks",
           "ghosting_error"]

TRAIL_FRAMES = 4
CHANGE_THRESHOLD = 0.1  # display-encoded units ([0, 1]): about a tenth of the displayed range
GHOSTING_DEFINITION = (
    "trail region of frame t = pixels whose reference changed in one of the last {frames} frames (frame t "
    "included), followed along the motion vectors; a pixel changed when the 3x3 mean of frame t's display-encoded "
    "reference differs by more than {threshold:g} (in some channel) from the 3x3 mean of frame t-1's reference "
    "warped by frame t's motion. Ghost error = mean |display_encode(output) - display_encode(reference)| over the "
    "trail's pixels and channels of a frame (0..1, lower is better), averaged over the frames whose trail is "
    "non-empty; ghost PSNR = the PSNR of those pixels (dB, higher is better), averaged the same way."
).format(frames=TRAIL_FRAMES, threshold=CHANGE_THRESHOLD)


def _check(references: torch.Tensor, motions: torch.Tensor, camera_cuts: Sequence[bool] | None) -> list[bool]:
    if references.dim() != 4 or references.shape[1] != 3:
        raise ValueError(f"references must be (T, 3, H, W), got {tuple(references.shape)}")
    if motions.dim() != 4 or motions.shape[1] != 2 or motions.shape[0] != references.shape[0]:
        raise ValueError(f"motions must be (T, 2, h, w) for {references.shape[0]} frames, got "
                         f"{tuple(motions.shape)}")
    (height, width), (low_height, low_width) = references.shape[-2:], motions.shape[-2:]
    if height % low_height or width % low_width or height // low_height != width // low_width:
        raise ValueError(f"references ({width}x{height}) must be the motion's resolution ({low_width}x{low_height}) "
                         "times one integer scale")
    frames = references.shape[0]
    cuts = [False] * frames if camera_cuts is None else [bool(c) for c in camera_cuts]
    if len(cuts) != frames:
        raise ValueError(f"camera_cuts has {len(cuts)} entries for {frames} frames")
    return cuts


def _motion_at(references: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """Motion (1, 2, h, w) at render resolution, expressed at the references' resolution."""
    scale = references.shape[-1] // motion.shape[-1]
    return motion if scale == 1 else upscale_motion(motion, scale)


def changed_regions(references: torch.Tensor, motions: torch.Tensor, camera_cuts: Sequence[bool] | None = None,
                    threshold: float = CHANGE_THRESHOLD) -> torch.Tensor:
    """Where each frame's reference changed from the previous one, beyond what the motion explains.

    references: (T, 3, H, W) linear HDR; motions: (T, 2, h, w) at render resolution (H = s h, W = s w);
    camera_cuts[t] True when frame t starts a new shot. Returns (T, 1, H, W) bool (see the module docstring):
    frame t changed where, in some channel, the 3x3 mean of display_encode(reference_t) and the 3x3 mean of
    display_encode(reference_{t-1}) warped by motion_t differ by more than ``threshold`` (windows clamped at the
    image border). Frame 0 and frames after a cut are all False.
    """
    cuts = _check(references, motions, camera_cuts)
    encoded = display_encode(references.float())
    changed = torch.zeros_like(encoded[:, :1], dtype=torch.bool)
    for t in range(1, encoded.shape[0]):
        if cuts[t]:
            continue
        motion = _motion_at(references, motions[t:t + 1].float())
        predicted, _ = backward_warp(encoded[t - 1:t], motion, mode="bilinear", padding="border")
        difference = _window_mean(encoded[t:t + 1]) - _window_mean(predicted)
        changed[t] = difference.abs().amax(dim=1) > threshold
    return changed


def _window_mean(image: torch.Tensor) -> torch.Tensor:
    """3x3 mean of every pixel, the window clamped at the image border (edge pixels repeated)."""
    return F.avg_pool2d(F.pad(image, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


def trail_masks(references: torch.Tensor, motions: torch.Tensor, camera_cuts: Sequence[bool] | None = None, *,
                frames: int = TRAIL_FRAMES, threshold: float = CHANGE_THRESHOLD) -> torch.Tensor:
    """The trail region of every frame: (T, 1, H, W) bool, True where the reference changed (``changed_regions``)
    in one of the last ``frames`` frames, frame t included, followed along the motion vectors.

    A per-pixel age (frames since the last change) is carried from frame t-1 to frame t by a nearest warp with
    frame t's motion and increased by one; it is 0 where frame t changed; pixels whose history lies outside the
    image, frame 0 and frames after a camera cut start with no trail. The trail is age < ``frames``.
    """
    if frames < 1:
        raise ValueError(f"the trail must last at least one frame, got {frames}")
    cuts = _check(references, motions, camera_cuts)
    changed = changed_regions(references, motions, cuts, threshold)
    never = float(frames)
    age = torch.full_like(changed[:1], never, dtype=torch.float32)
    trails = torch.zeros_like(changed)
    for t in range(changed.shape[0]):
        if t == 0 or cuts[t]:
            age = torch.full_like(age, never)
        else:
            motion = _motion_at(references, motions[t:t + 1].float())
            carried, inside = backward_warp(age, motion, mode="nearest", padding="border")
            age = torch.where(inside, (carried + 1).clamp(max=never), torch.full_like(carried, never))
        age = torch.where(changed[t:t + 1], torch.zeros_like(age), age)
        trails[t] = age[0] < never
    return trails


def ghosting_error(outputs: torch.Tensor, references: torch.Tensor, trails: torch.Tensor) -> dict | None:
    """A method's ghosting on one sequence: its error against the reference inside the trail region.

    outputs, references: (T, 3, H, W) linear HDR; trails: (T, 1, H, W) bool (``trail_masks``). For every frame
    whose trail is non-empty, on display-encoded images: the mean absolute error over the trail's pixels and
    channels, and the PSNR of those pixels (peak 1, capped at PSNR_CAP_DB). Returns {"error": mean of the per-frame
    errors (lower is better), "psnr": mean of the per-frame PSNRs (dB), "frames": how many frames have a trail,
    "per_frame_error": [error, or None where the trail is empty]}, or None when no frame has a trail.
    """
    if outputs.shape != references.shape or outputs.dim() != 4:
        raise ValueError(f"expected outputs and references of one (T, C, H, W) shape, got {tuple(outputs.shape)} "
                         f"and {tuple(references.shape)}")
    if trails.shape != (references.shape[0], 1, *references.shape[-2:]) or trails.dtype != torch.bool:
        raise ValueError(f"trails must be a (T, 1, H, W) bool mask matching the references, got "
                         f"{tuple(trails.shape)} {trails.dtype}")
    per_frame: list[float | None] = []
    psnrs: list[float] = []
    floor = 10.0 ** (-PSNR_CAP_DB / 10.0)
    for output, reference, trail in zip(outputs, references, trails):
        if not bool(trail.any()):
            per_frame.append(None)
            continue
        difference = (display_encode(output.double()) - display_encode(reference.double()))[:, trail[0]]
        per_frame.append(float(difference.abs().mean()))
        psnrs.append(10.0 * torch.log10(1.0 / difference.square().mean().clamp_min(floor)).item())
    errors = [e for e in per_frame if e is not None]
    if not errors:
        return None
    return {"error": statistics.fmean(errors), "psnr": statistics.fmean(psnrs), "frames": len(errors),
            "per_frame_error": per_frame}
