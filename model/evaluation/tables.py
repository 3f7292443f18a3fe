"""Markdown table helpers shared by the evaluation, benchmark, right-sizing and stability reports.

Cells say "-" for a missing or non-finite number; large counts are written compactly (12.3k, 4.5M); rows and
alignment rules are built the same way in every report.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any


def usable(value: Any) -> bool:
    """A finite number (None, NaN, Inf and non-numbers are not)."""
    if value is None or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except TypeError:
        return False


def source_label(label: str, source: str | None, labels: list[str]) -> str:
    """``label``, or ``label (source)`` when other entries share it (a pretrained model and a fine-tune of one
    method), so rows and per-label summaries never merge two models."""
    if labels.count(label) > 1 and source not in (None, label):
        return f"{label} ({source})"
    return label


def cell(value: Any, fmt: str) -> str:
    """``fmt.format(value)``, or "-" when the value is missing or not finite."""
    return fmt.format(value) if usable(value) else "-"


def compact(value: Any) -> str:
    """A count in three significant digits with a k / M / G suffix (1.5k, 2.1M); "-" when missing."""
    if not usable(value):
        return "-"
    for limit, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= limit:
            return f"{value / limit:.3g}{suffix}"
    return f"{value:.3g}"


def cell_text(message: Any) -> str:
    """One line of text safe inside a Markdown table cell (white space folded, pipes escaped)."""
    return " ".join(str(message).split()).replace("|", "\\|")


def table_row(cells: Iterable[Any]) -> str:
    """A Markdown table row: ``| a | b | c |``."""
    return "| " + " | ".join(str(c) for c in cells) + " |"


def table_rule(alignment: str) -> str:
    """The line under a header, one letter per column: ``l`` left, ``r`` right (``"lrr"`` -> ``|---|---:|---:|``)."""
    marks = {"l": "---", "r": "---:"}
    return "|" + "|".join(marks[letter] for letter in alignment) + "|"
