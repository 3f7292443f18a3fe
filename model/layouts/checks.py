"""Warnings when imported frames look wrong: conventions that convert without error but mean something else.

A layout with a wrong motion sign, NDC read as pixels, view-space normals read as world space or an inverted depth
still yields valid frame bundles; only the data's consistency across frames gives it away. ``SequenceChecks``
looks at consecutive frames as they are imported and says what looks wrong and which layout key to try.

- Motion: warping the previous frame by the motion must match this frame better than not warping it. Compared on
  the references (or, without them, the noise-free albedo) over the whole sequence; when warping loses, the other
  sign, y direction and units are tried and the best is named.
- Normals: a static world-space normal follows its surface point unchanged from frame to frame, so the previous
  frame's normals warped by the motion match this frame's; view-space normals turn with the camera (checked on the
  quarter of tracked pixels that change most).
- Depth: in most shots the ground recedes towards the horizon, so depth grows from the bottom of the image to the
  top; a depth that shrinks upward in most frames is likely inverted (1/z, or a 0..1 buffer whose far is 0).
  And on a plane, 1 / planar depth is an exact affine function of the pixel position (for any field of view),
  while 1 / ray distance is not: a depth that fits it exactly on the largest flat surface is planar depth read as
  ray distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.ndimage
import torch

from model.io.frames import FrameBundle
from model.ops.warp import backward_warp

MIN_MOTION_PIXELS = 0.25  # mean |motion| below this: too little movement to judge the motion's convention
NORMAL_TURN_DEGREES = 1.5  # upper-quartile angle between tracked normals above this: they turn with the camera
PLANAR_RESIDUAL = 1e-4  # relative RMS of the affine fit of 1/depth below this: planar depth (ray distance: ~1e-2)
MIN_FLAT_PIXELS = 64
WORSE_THAN_UNWARPED = 1.1  # warping must lose to not warping by this factor to be reported (moving lights tie them)
BETTER_VARIANT_RATIO = 0.75  # another convention whose warp error is below this fraction of the imported one wins
# Other conventions tried on the imported motion: name -> (x, y) multiplier for an image of (width, height).
_MOTION_VARIANTS = {
    "as imported": lambda width, height: (1.0, 1.0),
    "the opposite sign (motion.points_to)": lambda width, height: (-1.0, -1.0),
    "y flipped (motion.y)": lambda width, height: (1.0, -1.0),
    "x flipped": lambda width, height: (-1.0, 1.0),
    "NDC turned into pixels (motion.units = \"ndc\")": lambda width, height: (width / 2, height / 2),
    "pixels read as NDC undone (motion.units = \"pixels\")": lambda width, height: (2 / width, 2 / height),
}


def warp_previous(image: np.ndarray, motion: np.ndarray, jitter=(0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """The previous frame's (H, W[, C]) image read at centre + jitter + motion (bilinear, ``model.ops.warp``), and
    where that position lies inside the image."""
    tensor = torch.from_numpy(np.ascontiguousarray(image if image.ndim == 3 else image[..., None])).permute(2, 0, 1)
    flow = torch.from_numpy(np.ascontiguousarray(motion)).permute(2, 0, 1)[None]
    warped, inside = backward_warp(tensor[None].float(), flow.float(), jitter=jitter)
    return warped[0].permute(1, 2, 0).numpy(), inside[0, 0].numpy()


def _guide(frame: FrameBundle) -> np.ndarray:
    """What to compare across frames: the scale-1 reference, tone-mapped x / (1 + x) so that a few very bright pixels
    (a lamp, a highlight) do not outweigh the rest, else the noise-free albedo."""
    if 1 in frame.references:
        reference = np.maximum(frame.references[1], 0.0)
        return reference / (1.0 + reference)
    return frame.albedo


@dataclass
class SequenceChecks:
    """Feed frames in order with ``add``; ``warnings()`` says what looks wrong. ``hints`` adds a layout's name."""

    hints: str = ""
    _previous: FrameBundle | None = None
    _warped_error: dict[str, float] = field(default_factory=lambda: dict.fromkeys(_MOTION_VARIANTS, 0.0))
    _unwarped_error: float = 0.0
    _motion_frames: int = 0
    _normal_angles: list[float] = field(default_factory=list)
    _depth_votes: list[bool] = field(default_factory=list)
    _planar_residuals: list[float] = field(default_factory=list)

    def add(self, frame: FrameBundle) -> None:
        self._check_depth(frame)
        previous, self._previous = self._previous, frame
        if previous is None or frame.camera_cut or previous.resolution != frame.resolution:
            return
        motion = frame.motion
        if np.abs(motion).mean() < MIN_MOTION_PIXELS:
            return
        self._motion_frames += 1
        current, before = _guide(frame), _guide(previous)
        for name, multiplier in _MOTION_VARIANTS.items():
            variant = motion * np.array(multiplier(frame.width, frame.height), np.float32)
            warped, _ = warp_previous(before, variant)
            self._warped_error[name] += float(np.abs(warped - current).mean())
        self._unwarped_error += float(np.abs(before - current).mean())
        self._check_normals(previous, frame)

    def _check_normals(self, previous: FrameBundle, frame: FrameBundle) -> None:
        warped_normal, inside = warp_previous(previous.normal, frame.motion, frame.jitter)
        warped_depth, _ = warp_previous(previous.depth, frame.motion, frame.jitter)
        # Same surface: the depth the previous frame had there is close (not disoccluded, not an edge).
        same = inside & (frame.depth > 0) & (np.abs(warped_depth[..., 0] - frame.depth) < 0.05 * frame.depth)
        if same.sum() < 16:
            return
        lengths = np.linalg.norm(warped_normal, axis=-1)
        cosine = np.sum(warped_normal * frame.normal, axis=-1) / np.maximum(lengths, 1e-6)
        # The upper quartile: a camera turning about the ground's normal leaves the ground's view-space normal as
        # it is, so only the other surfaces (often fewer than half the pixels) show the turn.
        angles = np.degrees(np.arccos(np.clip(cosine[same], -1, 1)))
        self._normal_angles.append(float(np.percentile(angles, 75)))

    def _check_depth(self, frame: FrameBundle) -> None:
        residual = flat_surface_residual(frame)
        if residual is not None:
            self._planar_residuals.append(residual)
        hit = frame.depth > 0
        third = frame.height // 3
        top, bottom = frame.depth[:third][hit[:third]], frame.depth[-third:][hit[-third:]]
        if third and top.size >= 8 and bottom.size >= 8:
            self._depth_votes.append(bool(np.median(top) < np.median(bottom)))

    def warnings(self) -> list[str]:
        found = []
        hint = f" of layout '{self.hints}'" if self.hints else ""
        if self._motion_frames:
            frames = self._motion_frames
            unwarped = self._unwarped_error / frames
            errors = {name: total / frames for name, total in self._warped_error.items()}
            imported = errors["as imported"]
            best = min(errors, key=errors.get)
            suggestion = f"; with {best} it would be {errors[best]:.4g}" if best != "as imported" else ""
            if imported > WORSE_THAN_UNWARPED * unwarped:
                found.append(f"motion: warping the previous frame by the motion vectors matches this frame worse "
                             f"than not warping at all (mean error {imported:.4g} against {unwarped:.4g}, over "
                             f"{frames} frames){suggestion}; check the motion conventions{hint} (points_to, y, "
                             f"units)")
            elif errors[best] < BETTER_VARIANT_RATIO * imported:
                found.append(f"motion: warping the previous frame by the motion vectors matches this frame with mean "
                             f"error {imported:.4g} (not warping: {unwarped:.4g}, over {frames} frames), but with "
                             f"{best} it would be {errors[best]:.4g}; check the motion conventions{hint}")
        if self._normal_angles and np.median(self._normal_angles) > NORMAL_TURN_DEGREES:
            found.append(f"normal: a quarter of the surfaces' normals turn by {np.median(self._normal_angles):.1f} "
                         f"degrees or more from one frame to the next; world-space normals do not move with the "
                         f"camera, so "
                         f"these look like view-space normals: set normal.space = \"view\"{hint}")
        if len(self._depth_votes) >= 1 and sum(self._depth_votes) > len(self._depth_votes) / 2:
            shrinking = sum(self._depth_votes)
            found.append(f"depth: in {shrinking} of {len(self._depth_votes)} frames the depth shrinks from the bottom "
                         f"of the image to the top, where the ground usually recedes; is it inverted (1/z, or a 0..1 "
                         f"depth buffer) or the image upside down? The frame bundle's depth is the distance to the "
                         f"hit point (depth.kind{hint})")
        planar = [residual for residual in self._planar_residuals if residual < PLANAR_RESIDUAL]
        if self._planar_residuals and len(planar) > len(self._planar_residuals) / 2:
            found.append(f"depth: on the largest flat surface 1/depth is an exact affine function of the pixel "
                         f"position (relative residual {np.median(planar):.2g} in {len(planar)} of "
                         f"{len(self._planar_residuals)} frames), as for planar depth (along the view axis); the frame "
                         f"bundle's depth is the distance along each ray, for which it is not: set depth.kind = "
                         f"\"planar\"{hint} with the field of view (unless the lens is very long)")
        return found


def flat_surface_residual(frame: FrameBundle) -> float | None:
    """Relative RMS residual of the best affine fit of 1/depth to the sample positions over the largest connected
    surface of one normal (None without one of MIN_FLAT_PIXELS pixels spanning a quarter of the image each way)."""
    hit = frame.depth > 0
    if hit.sum() < MIN_FLAT_PIXELS:
        return None
    keys = np.round(frame.normal * 500).astype(np.int64)
    keys = (keys[..., 0] * 1_000_003 + keys[..., 1]) * 1_000_003 + keys[..., 2]
    values, counts = np.unique(keys[hit], return_counts=True)
    region = hit & (keys == values[np.argmax(counts)])
    labels, count = scipy.ndimage.label(region)
    if count == 0:
        return None
    largest = labels == 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    ys, xs = np.nonzero(largest)
    if len(xs) < MIN_FLAT_PIXELS or np.ptp(xs) < frame.width / 4 or np.ptp(ys) < frame.height / 4:
        return None
    positions = np.stack([xs + 0.5 + frame.jitter[0], ys + 0.5 + frame.jitter[1], np.ones(len(xs))], axis=1)
    depth = frame.depth[largest].astype(np.float64)
    keep = np.ones(len(depth), bool)
    # A few rounds dropping outliers: parallel surfaces touching in the image (a box top before the floor) share
    # the normal but not the plane.
    for _ in range(4):
        coefficients, *_ = np.linalg.lstsq(positions[keep], 1.0 / depth[keep], rcond=None)
        residual = np.abs(1.0 / (positions @ coefficients) - depth) / depth
        keep = residual <= max(3 * float(np.median(residual[keep])), 1e-6)
        if keep.sum() < MIN_FLAT_PIXELS:
            return None
    return float(np.sqrt(np.mean(residual[keep] ** 2)))


def reprojection_psnr(previous: np.ndarray, current: np.ndarray, motion: np.ndarray | None) -> float:
    """PSNR (display-encoded, as the evaluation) of the previous image warped by ``motion`` (None: not warped)
    against the current one, over pixels whose warp lands inside the previous image."""
    if motion is None:
        warped, inside = previous, np.ones(previous.shape[:2], bool)
    else:
        warped, inside = warp_previous(previous, motion)
    encode = lambda image: np.clip(image, 0, 1) ** (1 / 2.2)  # noqa: E731
    error = float(np.mean((encode(warped) - encode(current))[inside] ** 2))
    return math.inf if error == 0 else 10 * math.log10(1 / error)
