"""Docstrings and comments say what code is and why, in a few lines; measured results live in docs/results.

A module docstring of the packages holds at most ``MAX_MODULE_DOCSTRING_LINES`` lines (longer reasoning goes to the
guide under docs/ that covers the module), and no docstring or comment carries a measured figure: a number with dB,
JOD, GFLOP/s or ms, an "Nx faster", or the history of what was tried and not shipped. Those change with every
measurement, and the reports under docs/results hold them.
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("model", "core", "service", "workers", "cli", "client")
MAX_MODULE_DOCSTRING_LINES = 25
# A number followed by a unit of a measurement. A bound written as a comparison ("PSNR >= 30 dB", a target) is not a
# measurement, nor is a unit without a number ("PSNR in dB").
MEASURED = re.compile(
    r"(?<![<>]=\s)(?<![\w.])\d+(?:\.\d+)?\s?(?:dB|JOD|GFLOP)\b"
    r"|(?<![<>]=\s)(?<![\w.])\d+(?:\.\d+)?\s?ms\b"
    r"|\b\d+(?:\.\d+)?x (?:faster|slower)\b"
    r"|tried, not shipped",
)


def _sources() -> list[Path]:
    return sorted(path for package in PACKAGES for path in (ROOT / package).rglob("*.py")
                  if "__pycache__" not in path.parts)


def _docstrings(tree: ast.Module) -> list[tuple[int, str]]:
    """(first line, text) of the module's docstring and of every class's and function's."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            text = ast.get_docstring(node, clean=False)
            if text is not None:
                found.append((node.body[0].lineno, text))
    return found


def _comments(source: str) -> list[tuple[int, str]]:
    return [(token.start[0], token.string) for token in tokenize.generate_tokens(io.StringIO(source).readline)
            if token.type == tokenize.COMMENT]


def measured_figures(source: str) -> list[tuple[int, str]]:
    """(line, matched text) of every measured figure in the docstrings and comments of ``source``."""
    found = []
    for start, text in _docstrings(ast.parse(source)) + _comments(source):
        for offset, line in enumerate(text.splitlines()):
            found += [(start + offset, match.group(0)) for match in MEASURED.finditer(line)]
    return found


def test_module_docstrings_are_short():
    long = []
    for path in _sources():
        text = ast.get_docstring(ast.parse(path.read_text()), clean=False)
        if text is not None and len(text.splitlines()) > MAX_MODULE_DOCSTRING_LINES:
            long.append(f"{path.relative_to(ROOT)}: {len(text.splitlines())} lines")
    assert not long, (f"module docstrings over {MAX_MODULE_DOCSTRING_LINES} lines (keep what and why, move the "
                      "rest to the module's guide under docs/):\n" + "\n".join(long))


def test_no_docstring_or_comment_carries_a_measured_figure():
    figures = [f"{path.relative_to(ROOT)}:{line}: {text!r}" for path in _sources()
               for line, text in measured_figures(path.read_text())]
    assert not figures, "measured figures belong in docs/results, not in code:\n" + "\n".join(figures)


@pytest.mark.parametrize("text", ['"""+0.78 dB held out."""', '"""took 2.3 ms here."""', "# 8.65 JOD\n",
                                  '"""2.5x faster on this CPU."""', '"""120 GFLOP/s."""',
                                  '"""The low band: tried, not shipped."""'])
def test_the_rule_sees_measured_figures(text):
    assert measured_figures(text)


@pytest.mark.parametrize("text", ['"""PSNR in dB, higher is better."""', '"""e.g. \'validation PSNR >= 30 dB\'."""',
                                  '"""JOD (10 = no visible difference)."""', '"""max_ms_per_frame: a budget."""',
                                  "# ms per frame, GFLOP/s of the convolutions\n", '"""a 2x2 mean; 2x upscaling."""'])
def test_the_rule_leaves_units_and_bounds_alone(text):
    assert not measured_figures(text)
