"""docs/ stays a small set of guides and indexed results: its size, no EXR, every picture shown, every report
indexed, every relative link alive."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
RESULTS = DOCS / "results"
MAX_BYTES = 10 * 1024**2
MAX_JSON_BYTES = 64 * 1024
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)|<img [^>]*src=\"([^\"]+)\"")


def _pages() -> list[Path]:
    return [ROOT / "README.md", *sorted(DOCS.rglob("*.md"))]


def _links(page: Path) -> list[str]:
    return [a or b for a, b in LINK.findall(page.read_text()) if not (a or b).startswith(("http://", "https://"))]


def test_docs_is_small_and_holds_no_exr():
    files = [path for path in DOCS.rglob("*") if path.is_file()]
    assert sum(path.stat().st_size for path in files) < MAX_BYTES
    assert not [path for path in files if path.suffix.lower() == ".exr"]


def test_json_reports_in_docs_are_small():
    # a report may keep its small JSON beside its Markdown (the speed reports); larger outputs go to var/results/
    assert not [str(path.relative_to(ROOT)) for path in DOCS.rglob("*.json") if path.stat().st_size > MAX_JSON_BYTES]


def test_every_picture_in_docs_is_shown_by_a_page():
    shown = {(page.parent / link).resolve() for page in _pages() for link in _links(page)}
    pictures = [path for path in DOCS.rglob("*") if path.suffix.lower() in (".png", ".jpg", ".jpeg", ".svg", ".gif")]
    assert not [str(path.relative_to(ROOT)) for path in pictures if path.resolve() not in shown]


def test_every_relative_link_of_the_docs_exists():
    broken = [f"{page.relative_to(ROOT)}: {link}" for page in _pages() for link in _links(page)
              if not (page.parent / link).exists()]
    assert not broken


def test_the_results_index_names_every_report():
    index = (RESULTS / "README.md").read_text()
    reports = [path for path in RESULTS.iterdir() if path.name != "README.md"]
    assert not [path.name for path in reports if path.name not in index]
