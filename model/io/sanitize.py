"""Input sanitizing: the one place where NaN, Inf and out-of-range values in a frame's buffers are repaired.

Data read from disk is validated (``model.io.frames``) and never holds them, but a live renderer can send a NaN
from a degenerate path, an Inf from a zero pdf, or garbage in a guide buffer. A method must not propagate such a
value into its history (one NaN pixel poisons every later frame through the temporal blend), so every frame a method
steps on goes through ``sanitize_frame`` first, which returns the repaired frame and a ``SanitizeReport`` counting
the repaired pixels per buffer. Each repair keeps the frame consistent: bad radiance takes ``diffuse + specular`` or
0 (the split still sums to ``color``), guides are zeroed or clamped to their ranges, bad normals become "nothing
hit" or are renormalized, a non-finite depth becomes the frame's farthest finite depth (far enough to fail the
geometry test without flattening a depth normalized by its maximum), bad motion and jitter 0. Values within the
format's tolerance of a range (``model.io.frames.BUFFERS``) are clamped without being counted, so a valid frame
reports nothing. References are never touched: a method does not see them.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace

import torch

from model.io.frames import BUFFERS, JITTER_LIMIT, NORMAL_LENGTH_TOLERANCE
from model.methods.base import FrameBatch

__all__ = ["PLAIN_RANGES", "SanitizeReport", "bounds_need_no_repair", "sanitize_frame", "RADIANCE_BUFFERS"]

RADIANCE_BUFFERS = ("color", "diffuse", "specular")
UNIT_BUFFERS = {"albedo": 0.0, "specular_albedo": 0.0, "roughness": 1.0}  # buffer -> replacement for NaN/Inf


@dataclass
class SanitizeReport:
    """Pixels repaired per buffer: ``non_finite`` (NaN or Inf) and ``out_of_range`` (clamped or renormalized)."""

    non_finite: dict[str, int] = field(default_factory=dict)
    out_of_range: dict[str, int] = field(default_factory=dict)
    frames: int = 0

    @property
    def total(self) -> int:
        return sum(self.non_finite.values()) + sum(self.out_of_range.values())

    @property
    def clean(self) -> bool:
        return self.total == 0

    def __add__(self, other: SanitizeReport) -> SanitizeReport:
        def merged(a: dict[str, int], b: dict[str, int]) -> dict[str, int]:
            return {name: a.get(name, 0) + b.get(name, 0) for name in {**a, **b}}

        return SanitizeReport(merged(self.non_finite, other.non_finite), merged(self.out_of_range, other.out_of_range),
                              self.frames + other.frames)

    def to_dict(self) -> dict:
        """JSON form: only buffers with repairs, in the format's buffer order, plus totals."""
        def nonzero(counts: dict[str, int]) -> dict[str, int]:
            order = list(BUFFERS) + ["jitter"]
            return {name: counts[name] for name in sorted(counts, key=order.index) if counts[name]}

        return {"frames": self.frames, "total": self.total, "non_finite": nonzero(self.non_finite),
                "out_of_range": nonzero(self.out_of_range)}

    def describe(self) -> str:
        """One line, e.g. 'color: 12 non-finite; depth: 3 non-finite, 1 out of range' ('clean' when none)."""
        parts = []
        names = [n for n in list(BUFFERS) + ["jitter"] if self.non_finite.get(n) or self.out_of_range.get(n)]
        for name in names:
            counts = []
            if self.non_finite.get(name):
                counts.append(f"{self.non_finite[name]} non-finite")
            if self.out_of_range.get(name):
                counts.append(f"{self.out_of_range[name]} out of range")
            parts.append(f"{name}: {', '.join(counts)}")
        return "; ".join(parts) if parts else "clean"


def _bad_pixels(tensor: torch.Tensor) -> torch.Tensor:
    """(N, 1, H, W) bool: pixels with a NaN or Inf in any channel."""
    return ~torch.isfinite(tensor).all(dim=1, keepdim=True)


def _count(mask: torch.Tensor) -> int:
    return int(mask.sum())


def _clamp_counted(tensor: torch.Tensor, low: float | None, high: float | None,
                   tolerance: float) -> tuple[torch.Tensor, int]:
    """Clamp into [low, high] (the tensor itself when already inside); count pixels that were outside by more
    than ``tolerance``."""
    below = low is not None and bool((tensor < low).any())
    above = high is not None and bool((tensor > high).any())
    if not (below or above):
        return tensor, 0
    outside = torch.zeros_like(tensor, dtype=torch.bool)
    if below:
        outside |= tensor < low - tolerance
    if above:
        outside |= tensor > high + tolerance
    return tensor.clamp(min=low, max=high), _count(outside.any(dim=1, keepdim=True))


def _radiance(frame: FrameBatch, report: SanitizeReport) -> dict[str, torch.Tensor]:
    color, diffuse, specular = frame.color, frame.diffuse, frame.specular
    color_bad = _bad_pixels(color)
    report.non_finite["color"] = _count(color_bad)
    repaired: dict[str, torch.Tensor] = {}
    if diffuse is not None and specular is not None:
        diffuse_bad, specular_bad = _bad_pixels(diffuse), _bad_pixels(specular)
        report.non_finite["diffuse"] = _count(diffuse_bad)
        report.non_finite["specular"] = _count(specular_bad)
        split_ok = ~(diffuse_bad | specular_bad)
        zero = torch.zeros((), dtype=color.dtype, device=color.device)
        if bool(color_bad.any()) or not bool(split_ok.all()):
            summed = torch.where(split_ok, diffuse + specular, zero)
            color, diffuse, specular = (torch.where(color_bad, summed, color),
                                        torch.where(split_ok, diffuse, torch.where(color_bad, zero, color)),
                                        torch.where(split_ok, specular, zero))
        repaired["diffuse"], repaired["specular"] = diffuse, specular
    else:
        # Color alone (or, against the format, only one half of the split): each buffer on its own.
        for name in ("diffuse", "specular"):
            tensor = getattr(frame, name)
            if tensor is not None:
                report.non_finite[name] = _count(_bad_pixels(tensor))
                repaired[name] = tensor
    repaired["color"] = color
    for name, tensor in repaired.items():
        # NaN/Inf left here (color without a split, or a finite sum that overflowed) become 0; then negatives.
        if not bool(torch.isfinite(tensor).all()):
            tensor = torch.nan_to_num(tensor, nan=0.0, posinf=0.0, neginf=0.0)
        repaired[name], report.out_of_range[name] = _clamp_counted(tensor, 0.0, None, BUFFERS[name].tolerance)
    return repaired


def _unit_range(name: str, tensor: torch.Tensor, report: SanitizeReport) -> torch.Tensor:
    bad = _bad_pixels(tensor)
    report.non_finite[name] = _count(bad)
    if bool(bad.any()):
        tensor = torch.where(torch.isfinite(tensor), tensor, torch.full((), UNIT_BUFFERS[name], dtype=tensor.dtype,
                                                                        device=tensor.device))
    tensor, report.out_of_range[name] = _clamp_counted(tensor, 0.0, 1.0, BUFFERS[name].tolerance)
    return tensor


def _zeroed_bad_pixels(name: str, tensor: torch.Tensor, report: SanitizeReport) -> torch.Tensor:
    """The tensor with every pixel that has a NaN or Inf in any channel set to 0 in all channels, counted as
    non-finite: the repair of normal ("nothing hit") and motion (no motion), see the module docstring."""
    bad = _bad_pixels(tensor)
    report.non_finite[name] = _count(bad)
    if bool(bad.any()):
        tensor = torch.where(bad, torch.zeros((), dtype=tensor.dtype, device=tensor.device), tensor)
    return tensor


def _normal(normal: torch.Tensor, report: SanitizeReport) -> torch.Tensor:
    normal = _zeroed_bad_pixels("normal", normal, report)
    length = torch.linalg.vector_norm(normal.double(), dim=1, keepdim=True)
    off = (length > 0) & ((length - 1).abs() > NORMAL_LENGTH_TOLERANCE)
    report.out_of_range["normal"] = _count(off)
    if bool(off.any()):
        normal = torch.where(off, (normal.double() / length.clamp_min(1e-300)).to(normal.dtype), normal)
    return normal


def _depth(depth: torch.Tensor, report: SanitizeReport) -> torch.Tensor:
    bad = ~torch.isfinite(depth)
    report.non_finite["depth"] = _count(bad)
    if bool(bad.any()):
        finite = torch.where(bad, torch.zeros((), dtype=depth.dtype, device=depth.device), depth)
        farthest = finite.amax(dim=(1, 2, 3), keepdim=True).clamp_min(0.0)
        depth = torch.where(bad, farthest.expand_as(depth), depth)
    depth, report.out_of_range["depth"] = _clamp_counted(depth, 0.0, None, BUFFERS["depth"].tolerance)
    return depth


def _jitter(jitter: torch.Tensor, report: SanitizeReport) -> torch.Tensor:
    bad = ~torch.isfinite(jitter).all(dim=1)
    report.non_finite["jitter"] = _count(bad)
    outside = (jitter.abs() > JITTER_LIMIT).any(dim=1) & ~bad
    report.out_of_range["jitter"] = _count(outside)
    if bool(bad.any()) or bool(outside.any()):
        jitter = torch.nan_to_num(jitter, nan=0.0, posinf=0.0, neginf=0.0).clamp(-JITTER_LIMIT, JITTER_LIMIT)
    return jitter


# The range each buffer's values keep without a repair (None: unbounded); any other buffer only has to be finite.
PLAIN_RANGES: dict[str, tuple[float | None, float | None]] = {
    "color": (0.0, None), "diffuse": (0.0, None), "specular": (0.0, None), "albedo": (0.0, 1.0),
    "specular_albedo": (0.0, 1.0), "roughness": (0.0, 1.0), "depth": (0.0, None), "motion": (None, None)}


def bounds_need_no_repair(bounds: Mapping[str, tuple[float, float]], jitter: Iterable[float]) -> bool:
    """Whether each buffer's lowest and highest value (``bounds``, by name) and the jitter show nothing to repair:
    all finite, each inside its PLAIN_RANGES entry. Normal lengths are not judged here (``_plainly_valid`` checks
    them; a stream frame proves them where it is read, service.sessions.stream_batch)."""
    for name, (lowest, highest) in bounds.items():
        if not (math.isfinite(lowest) and math.isfinite(highest)):
            return False
        low, high = PLAIN_RANGES.get(name, (None, None))
        if (low is not None and lowest < low) or (high is not None and highest > high):
            return False
    return all(math.isfinite(value) and abs(value) <= JITTER_LIMIT for value in jitter)


def _plainly_valid(frame: FrameBatch) -> bool:
    """True when one min/max per buffer shows nothing to repair (min and max propagate NaN); False means "look
    pixel by pixel", not that something is wrong. It is much cheaper than the pixel-wise pass, which a session
    would otherwise pay on every frame."""
    bounds = {}
    for name in PLAIN_RANGES:
        tensor = getattr(frame, name)
        if tensor is not None:
            lowest, highest = (float(v) for v in torch.aminmax(tensor))
            bounds[name] = (lowest, highest)
    if not bounds_need_no_repair(bounds, frame.jitter.reshape(-1).tolist()):
        return False
    squared = (frame.normal * frame.normal).sum(dim=1)
    # |n|^2 within (1 +- tol)^2 where anything was hit, or exactly 0: no normal is renormalized.
    inside = (squared == 0) | (((1 - NORMAL_LENGTH_TOLERANCE) ** 2 < squared)
                               & (squared < (1 + NORMAL_LENGTH_TOLERANCE) ** 2))
    return bool(inside.all())


def sanitize_frame(frame: FrameBatch) -> tuple[FrameBatch, SanitizeReport]:
    """The frame with every NaN, Inf and out-of-range value repaired (see the module docstring), and the counts.

    A frame that one min/max per buffer shows to be valid is returned as it is; otherwise tensors that need no
    repair are returned as they are (no copy).
    """
    report = SanitizeReport(frames=frame.batch_size)
    if _plainly_valid(frame):
        return frame, report
    changes: dict[str, torch.Tensor] = dict(_radiance(frame, report))
    for name in UNIT_BUFFERS:
        tensor = getattr(frame, name)
        if tensor is not None:
            changes[name] = _unit_range(name, tensor, report)
    changes["normal"] = _normal(frame.normal, report)
    changes["depth"] = _depth(frame.depth, report)
    changes["motion"] = _zeroed_bad_pixels("motion", frame.motion, report)
    changes["jitter"] = _jitter(frame.jitter, report)
    changes = {name: tensor for name, tensor in changes.items() if tensor is not getattr(frame, name)}
    return (replace(frame, **changes) if changes else frame), report
