"""The ladder as a report: a Markdown table with its caption and choice, and the files ``ladder.json`` and
``ladder.md``."""

from __future__ import annotations

import json
from pathlib import Path

from model.fit.choice import LadderResult
from model.evaluation.tables import cell, compact, table_row, table_rule

LADDER_JSON = "ladder.json"
LADDER_MARKDOWN = "ladder.md"


def format_ladder(result: LadderResult) -> str:
    """The ladder as a Markdown table with a caption (what was measured, how) and the choice below it."""
    info = result.info
    timing = info.get("timing", {})
    caption = (f"{result.family} at scale {result.scale}, target {result.target} "
               f"({result.target.describe(result.bar)})")
    if timing:
        caption += (f"; ms per frame: median of {timing.get('frames')} frames after {timing.get('warmup_frames')} "
                    f"warm-up, render {timing.get('resolution')} -> output {timing.get('output_resolution')}, "
                    f"{timing.get('threads')} threads, {timing.get('device')}")
    if info.get("validation"):
        caption += f"; quality on {info['validation']}"
    lines = [caption, "", table_row(["preset", "FLOPs/px", "params", "ms/frame", "PSNR dB", "SSIM", "FLIP", "status",
                                     "meets"]), table_rule("lrrrrrrll")]
    for rung in result.rungs:
        name = f"**{rung.preset}** (chosen)" if rung.chosen else rung.preset
        meets = "-" if rung.meets is None else ("yes" if rung.meets else "no")
        status = rung.status if rung.measured else f"skipped: {rung.note}" if rung.note else "skipped"
        lines.append(table_row([name, compact(rung.flops_per_pixel), compact(rung.params),
                                cell(rung.ms_per_frame, "{:.3g}"), cell(rung.psnr, "{:.2f}"), cell(rung.ssim, "{:.4f}"),
                                cell(rung.flip, "{:.4f}"), status, meets]))
    lines += ["", f"choice: {result.reason}"]
    registered = info.get("registered")
    if registered:
        lines.append(f"registered: {registered['uri']} (alias {info.get('alias')!r} -> version {registered['version']})")
    return "\n".join(lines)


def write_ladder(result: LadderResult, folder: Path) -> dict[str, Path]:
    """``ladder.json`` (the whole result) and ``ladder.md`` (``format_ladder``) in ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = {LADDER_JSON: folder / LADDER_JSON, LADDER_MARKDOWN: folder / LADDER_MARKDOWN}
    paths[LADDER_JSON].write_text(json.dumps(result.to_dict(), indent=2) + "\n")
    paths[LADDER_MARKDOWN].write_text(format_ladder(result) + "\n")
    return paths
