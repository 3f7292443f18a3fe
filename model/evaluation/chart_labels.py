"""Point labels that never overlap each other, the points or the legend, and stay inside the axes.

A deterministic greedy placement, done once the figure's layout is final: for each point (the most crowded
first) a fixed list of candidate positions around it, in rings of growing distance and sixteen directions, is
scored by its overlap with the labels already placed, every point's marker and the legend; the first candidate
of least score wins, nearer rings first. Labels set apart from their point get a thin leader line. Only when no
candidate inside the axes is free (more labels than room) does a label overlap; it still stays inside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.text import Text
from matplotlib.transforms import Bbox

RINGS = (4, 10, 18, 28, 40, 55, 72, 92, 115, 140)  # candidate distances from the point, in points (1/72 inch)
DIRECTIONS = 16
LEADER_FROM = 10  # rings at least this far get a leader line
MARKER_RADIUS = 4.5  # points: the benchmark's markers (s=36, 6 pt across) with an edge


@dataclass
class PointLabel:
    x: float
    y: float
    text: str


def freeze_layout(figure: Figure):
    """Draw once (the layout engine places the axes, a "best" legend picks its corner), then keep both where they
    are, so that labels placed afterwards cannot move them. Returns the renderer."""
    canvas = figure.canvas if isinstance(figure.canvas, FigureCanvasAgg) else FigureCanvasAgg(figure)
    canvas.draw()
    figure.set_layout_engine("none")
    renderer = canvas.get_renderer()
    for axis in figure.axes:
        legend = axis.get_legend()
        if legend is not None:
            corner = axis.transAxes.inverted().transform(legend.get_window_extent(renderer).p0)
            legend.set_loc(tuple(float(v) for v in corner))
    return renderer


def place_labels(axis, labels: list[PointLabel], renderer, fontsize: float = 7) -> list:
    """Annotate every label's point on ``axis`` (layout frozen: ``freeze_layout``); returns the annotations."""
    if not labels:
        return []
    scale = axis.figure.dpi / 72.0  # points -> display pixels
    frame = axis.get_window_extent(renderer)
    anchors = [tuple(axis.transData.transform((label.x, label.y))) for label in labels]
    radius = MARKER_RADIUS * scale
    obstacles = [Bbox.from_extents(px - radius, py - radius, px + radius, py + radius) for px, py in anchors]
    legend = axis.get_legend()
    if legend is not None:
        obstacles.append(legend.get_window_extent(renderer))
    sizes = [_text_size(axis, label.text, fontsize, renderer) for label in labels]
    placed: list[Bbox] = []
    annotations = [None] * len(labels)
    for index in _crowded_first(anchors, 40 * scale):
        (px, py), (width, height) = anchors[index], sizes[index]
        best = None
        for distance, angle, box, alignment in _candidates(px, py, width, height, scale):
            score = _outside(box, frame) * 1e9 + sum(_overlap(box, other) for other in (*placed, *obstacles))
            if best is None or score < best[0]:
                best = (score, distance, angle, box, alignment)
            if score == 0:
                break  # candidates come nearest first: the first free one is the best
        _, distance, angle, box, (ha, va) = best
        box = _clamped(box, frame)
        placed.append(box)
        # The annotation's anchor: the box corner or edge middle the alignment names, as an offset in points.
        anchor_x = {"left": box.x0, "right": box.x1, "center": (box.x0 + box.x1) / 2}[ha]
        anchor_y = {"bottom": box.y0, "top": box.y1, "center": (box.y0 + box.y1) / 2}[va]
        leader = dict(arrowstyle="-", color="0.45", linewidth=0.5, shrinkA=0, shrinkB=radius / scale)
        annotations[index] = axis.annotate(
            labels[index].text, (labels[index].x, labels[index].y), textcoords="offset points",
            xytext=((anchor_x - px) / scale, (anchor_y - py) / scale), ha=ha, va=va, fontsize=fontsize, zorder=4,
            arrowprops=leader if distance >= LEADER_FROM else None)
    return annotations


def _text_size(axis, text: str, fontsize: float, renderer) -> tuple[float, float]:
    probe = Text(0, 0, text, fontsize=fontsize)
    probe.set_figure(axis.figure)
    box = probe.get_window_extent(renderer)
    return box.width, box.height


def _crowded_first(anchors: list[tuple[float, float]], reach: float) -> list[int]:
    def neighbours(i: int) -> int:
        xi, yi = anchors[i]
        return sum(1 for j, (xj, yj) in enumerate(anchors) if j != i and math.hypot(xi - xj, yi - yj) < reach)

    return sorted(range(len(anchors)), key=lambda i: (-neighbours(i), i))


def _candidates(px: float, py: float, width: float, height: float, scale: float):
    """(distance, angle, box, (ha, va)) around (px, py), nearest ring first, upper right first within a ring."""
    for distance in RINGS:
        for step in range(DIRECTIONS):
            angle = math.pi / 4 + 2 * math.pi * step / DIRECTIONS
            dx, dy = math.cos(angle), math.sin(angle)
            ax, ay = px + distance * scale * dx, py + distance * scale * dy
            ha = "left" if dx > 0.3 else "right" if dx < -0.3 else "center"
            va = "bottom" if dy > 0.3 else "top" if dy < -0.3 else "center"
            x0 = {"left": ax, "right": ax - width, "center": ax - width / 2}[ha]
            y0 = {"bottom": ay, "top": ay - height, "center": ay - height / 2}[va]
            yield distance, angle, Bbox.from_bounds(x0, y0, width, height), (ha, va)


def _overlap(a: Bbox, b: Bbox) -> float:
    return max(0.0, min(a.x1, b.x1) - max(a.x0, b.x0)) * max(0.0, min(a.y1, b.y1) - max(a.y0, b.y0))


def _outside(box: Bbox, frame: Bbox, margin: float = 2.0) -> float:
    return (max(0.0, frame.x0 + margin - box.x0) + max(0.0, box.x1 - frame.x1 + margin)
            + max(0.0, frame.y0 + margin - box.y0) + max(0.0, box.y1 - frame.y1 + margin))


def _clamped(box: Bbox, frame: Bbox, margin: float = 2.0) -> Bbox:
    """``box`` shifted inside ``frame`` (a label wider than the axes keeps its left edge inside)."""
    dx = max(0.0, frame.x0 + margin - box.x0) or min(0.0, frame.x1 - margin - box.x1)
    dy = max(0.0, frame.y0 + margin - box.y0) or min(0.0, frame.y1 - margin - box.y1)
    return Bbox.from_bounds(box.x0 + dx, box.y0 + dy, box.width, box.height)
