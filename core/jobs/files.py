"""The files of a job folder (``jobs/<id>/``) that the worker writes and the API serves, and reading a log's tail."""

from __future__ import annotations

import re
from pathlib import Path

LOG_FILE = "job.log"  # everything the job logged
DDP_LOG_FILE = "ddp.log"  # the DDP ranks' output
CHECKPOINT_FOLDER = "checkpoints"  # a train job's checkpoints
REPORT_JSON = "report.json"  # evaluate and benchmark reports
REPORT_MARKDOWN = "report.md"
CHART = "quality_speed.png"  # a benchmark's quality/speed chart
BENCHMARK_FILES = ("benchmark.json", "benchmark.md", "quality_cost.png")  # a benchmark's table and cost chart
# An evaluate job's side-by-side picture of each sequence's last frame: comparison_<sequence>.png (the name made
# safe for a URL path segment; comparison_x<scale>_<sequence>.png when the job ran at two scales).
COMPARISON = re.compile(r"^comparison_[A-Za-z0-9._-]+\.png$")
# A stability job's report and charts (as model.evaluation.stability_report.write_report names them).
STABILITY_FILES = ("stability.json", "stability.md", "psnr_curves.png", "psnr_drop.png", "ghost_curves.png")


def comparison_name(sequence: str, scale: int | None = None) -> str:
    """The file name of ``sequence``'s side-by-side picture (``scale`` given when a job ran at more than one)."""
    safe = re.sub(r"[^A-Za-z0-9._-]", "_", sequence)
    return f"comparison_{'' if scale is None else f'x{scale}_'}{safe}.png"


def tail_lines(path: Path, count: int, block: int = 64 * 1024) -> list[str]:
    """The last ``count`` lines of a text file, read from its end (a training log can grow large)."""
    if count <= 0 or not path.is_file():
        return []
    with path.open("rb") as handle:
        handle.seek(0, 2)
        position = handle.tell()
        data = b""
        while position > 0 and data.count(b"\n") <= count:
            step = min(block, position)
            position -= step
            handle.seek(position)
            data = handle.read(step) + data
    lines = data.decode("utf-8", errors="replace").splitlines()
    return lines[-count:]
