"""Per-frame speed of methods stepped side by side in one process: percentiles, peak memory, OIDN's part of a step.

``time_group`` steps several methods on the same frames, interleaved frame by frame (each frame in a rotated order,
so a busy machine slows them alike), after warm-up frames, and records each step's wall time with the device
synchronized, its peak memory, and the time of every OIDN call inside it (through ``intercepted_oidn``): the
learned part of a step is its time less its OIDN calls'. A method given a reference (the same weights as the
plain fp32 eager model, run on torch's ops without the native kernels) is also compared with it on the first frames:
max abs difference and PSNR.
``speed_rows`` turns the records into report rows with each learned model's time ratio to the OIDN rows of its
group; ``markdown_table`` and ``ratio_figure`` present them. The protocol: docs/benchmark.md.
"""

from __future__ import annotations

import math
import platform
import re
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch

from model.deployment.inference_forms import form_psnr
from model.evaluation.timing import synchronize, timed
from model.methods.oidn import intercepted_oidn
from model.ops import native

__all__ = ["GroupTiming", "MemoryProbe", "compare_outputs", "device_name", "file_stem", "learned_part",
           "markdown_table", "merge_rows", "percentile", "ratio_figure", "rounded", "speed_rows", "summary_ms",
           "time_group"]


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (0..100) with linear interpolation between the closest ranks (numpy's default)."""
    if not values:
        raise ValueError("no values to take a percentile of")
    ordered = sorted(values)
    rank = (len(ordered) - 1) * q / 100.0
    low = math.floor(rank)
    high = min(low + 1, len(ordered) - 1)
    return ordered[low] + (ordered[high] - ordered[low]) * (rank - low)


def summary_ms(seconds: Sequence[float]) -> dict[str, float | int]:
    """p50 and p95 of per-frame seconds, in milliseconds, with the frame count."""
    return {"p50_ms": 1000 * percentile(seconds, 50), "p95_ms": 1000 * percentile(seconds, 95),
            "frames": len(seconds)}


def learned_part(step_seconds: Sequence[float], oidn_seconds: Sequence[float]) -> dict[str, float]:
    """The learned part of a step that calls OIDN: per frame, the step's time less its OIDN calls' time. Returns
    the median OIDN time inside the step, the median learned time and the learned share (the median over frames of
    learned / step)."""
    if len(step_seconds) != len(oidn_seconds) or not step_seconds:
        raise ValueError("one OIDN time per timed step is needed")
    learned = [max(0.0, step - oidn) for step, oidn in zip(step_seconds, oidn_seconds)]
    return {"oidn_in_step_p50_ms": 1000 * percentile(oidn_seconds, 50),
            "learned_p50_ms": 1000 * percentile(learned, 50),
            "learned_share": percentile([part / step for part, step in zip(learned, step_seconds)], 50)}


def compare_outputs(outputs: Sequence[torch.Tensor], references: Sequence[torch.Tensor]) -> dict[str, float | int]:
    """How far a fast form's outputs are from the plain fp32 model's on the same frames: the largest absolute
    difference (linear radiance) and the lowest per-frame PSNR of the two tone-mapped (``form_psnr``)."""
    if len(outputs) != len(references) or not outputs:
        raise ValueError("one reference output per output is needed")
    return {"frames": len(outputs),
            "max_abs_diff": max(float((a.float() - b.float()).abs().max()) for a, b in zip(outputs, references)),
            "min_psnr_db": min(form_psnr(a.float().cpu(), b.float().cpu()) for a, b in zip(outputs, references))}


class MemoryProbe:
    """Peak memory during one step: on a GPU torch's allocator peak; on the CPU the process's peak resident set,
    reset before each step through /proc/self/clear_refs where Linux allows it (else the process's peak so far).
    ``step_mb``: the peak less what was held before the step."""

    def __init__(self, device: torch.device) -> None:
        self.device = device
        self.before = 0.0

    def start(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
            self.before = torch.cuda.memory_allocated(self.device) / 2 ** 20
            return
        try:
            with open("/proc/self/clear_refs", "w") as handle:
                handle.write("5")  # resets the peak resident set (VmHWM) to the current one
        except OSError:
            pass
        self.before = _status_mb("VmRSS")

    def peak(self) -> tuple[float, float]:
        if self.device.type == "cuda":
            peak = torch.cuda.max_memory_allocated(self.device) / 2 ** 20
        else:
            peak = _status_mb("VmHWM") or resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        return peak, max(0.0, peak - self.before)


def _status_mb(key: str) -> float:
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


@dataclass
class GroupTiming:
    """What ``time_group`` recorded for one method: per timed frame the step's and its OIDN calls' seconds, the
    largest peak and step memory, and the output check against its reference (None without one)."""

    seconds: list[float] = field(default_factory=list)
    oidn_seconds: list[float] = field(default_factory=list)
    peak_mb: float = 0.0
    step_mb: float = 0.0
    reference_seconds: list[float] = field(default_factory=list)
    check: dict[str, float | int] | None = None


def time_group(methods: dict[str, Any], frames: Sequence[Any], device: torch.device | str, *, warmup: int,
               references: dict[str, Any] | None = None, check_frames: int = 3,
               clock: Callable[[Callable[[], Any], torch.device], tuple[Any, float]] = timed) -> dict[str, GroupTiming]:
    """Step every method of ``methods`` (label -> method) over ``frames`` with its own history, interleaved frame
    by frame; the first ``warmup`` frames are not timed. ``references`` (label -> the same model in plain fp32) step
    the warm-up frames and the first ``check_frames`` timed ones, compared with the label's outputs on all of them
    (so on CUDA the check covers graph replays, which begin after the warm-up); their timed steps are
    ``reference_seconds``. ``clock`` times one call (tests give a fake one)."""
    device = torch.device(device)
    references = references or {}
    records = {label: GroupTiming() for label in methods}
    states: dict[str, Any] = dict.fromkeys(methods)
    reference_states: dict[str, Any] = dict.fromkeys(references)
    checked: dict[str, tuple[list[torch.Tensor], list[torch.Tensor]]] = {label: ([], []) for label in references}
    probe = MemoryProbe(device)
    labels = list(methods)
    with torch.inference_mode():
        for index, frame in enumerate(frames):
            for label in labels[index % len(labels):] + labels[:index % len(labels)]:
                oidn_calls: list[float] = []

                def timed_oidn(denoise, oidn_frame, quality):
                    result, elapsed = clock(lambda: denoise(oidn_frame, quality), device)
                    oidn_calls.append(elapsed)
                    return result

                probe.start()
                with intercepted_oidn(timed_oidn):
                    (output, states[label]), elapsed = clock(
                        lambda: methods[label].step(frame, states[label]), device)
                record = records[label]
                if index >= warmup:
                    peak, step = probe.peak()
                    record.peak_mb, record.step_mb = max(record.peak_mb, peak), max(record.step_mb, step)
                    record.seconds.append(elapsed)
                    record.oidn_seconds.append(sum(oidn_calls))
                if label in references and index < warmup + check_frames:
                    with native.disabled():  # the plain model: fp32 eager on torch's own ops
                        (reference, reference_states[label]), reference_elapsed = clock(
                            lambda: references[label].step(frame, reference_states[label]), device)
                    if index >= warmup:
                        record.reference_seconds.append(reference_elapsed)
                    checked[label][0].append(output.detach().clone())
                    checked[label][1].append(reference.detach().clone())
    synchronize(device)
    for label, (outputs, reference_outputs) in checked.items():
        if outputs:
            records[label].check = compare_outputs(outputs, reference_outputs)
    return records


def speed_rows(group: list[dict[str, Any]], records: dict[str, GroupTiming]) -> list[dict[str, Any]]:
    """Report rows of one group: each entry of ``group`` (``label``, ``method`` (the registry name),
    ``learned`` and whatever it describes of the model) with its timing; every learned row gets its time ratio to
    the group's ``oidn`` and ``oidn-taa`` rows (p50 / p50), and a learned row that calls OIDN its learned part."""
    rows = []
    for entry in group:
        record = records[entry["label"]]
        row = {key: value for key, value in entry.items() if key != "label"}
        row["model"] = entry["label"]
        row.update(summary_ms(record.seconds))
        row.update(peak_mb=record.peak_mb, step_mb=record.step_mb, check=record.check,
                   eager_p50_ms=1000 * percentile(record.reference_seconds, 50) if record.reference_seconds else None)
        if entry.get("learned") and any(record.oidn_seconds):
            row.update(learned_part(record.seconds, record.oidn_seconds))
        rows.append(row)
    peers = {row["method"]: row for row in rows if not row.get("learned")}
    for row in rows:
        if row.get("learned"):
            for peer in ("oidn", "oidn-taa"):
                if peer in peers:
                    row[f"ratio_to_{peer.replace('-', '_')}"] = row["p50_ms"] / peers[peer]["p50_ms"]
    return rows


def merge_rows(old: list[dict[str, Any]], new: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``old`` rows with those measured again in ``new`` (same model and output size) replaced, new ones added."""
    def key(row: dict[str, Any]) -> tuple[str, tuple[int, ...]]:
        return row["model"], tuple(row["output"])

    fresh = {key(row) for row in new}
    return [row for row in old if key(row) not in fresh] + list(new)


def rounded(value: Any, digits: int = 4) -> Any:
    """``value`` with every float rounded to ``digits`` significant digits (a report's JSON stays small and legible)."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}")
    if isinstance(value, dict):
        return {key: rounded(item, digits) for key, item in value.items()}
    if isinstance(value, list):
        return [rounded(item, digits) for item in value]
    return value


def device_name(device: torch.device | str) -> str:
    """The GPU's name, or the CPU's model name (from /proc/cpuinfo on Linux)."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    try:
        with open("/proc/cpuinfo") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "cpu"


def file_stem(name: str, device_type: str, threads: int) -> str:
    """``speed_<device>`` in lower case, the CPU's thread count added (``speed_intel-xeon-..._2-threads``)."""
    slug = re.sub(r"[^a-z0-9]+", "-", re.sub(r"\((r|tm)\)|\bcpu\b|@.*", "", name.lower())).strip("-")
    return f"speed_{slug or device_type}" + (f"_{threads}-threads" if device_type == "cpu" else "")


def _cell(value: float | None, fmt: str) -> str:
    return "-" if value is None else format(value, fmt)


def markdown_table(report: dict[str, Any]) -> str:
    """The report's rows as a Markdown table under one line naming the device, threads and frames."""
    device = report["device"]
    load = report.get("load_average")
    # a merged report holds one (start, end) pair per run
    load_text = f"load average {', '.join(f'{a:.1f} -> {b:.1f}' for a, b in zip(load[::2], load[1::2]))} " \
        f"(start -> end of each run), {device.get('cores')} cores; " if load else ""
    lines = [f"{device['name']} ({device['type']}, {device['threads']} torch threads); torch {report['torch']}; "
             f"{load_text}"
             f"per frame after {report['warmup']} warm-up frames; ratios are p50 / p50 of the same-quality OIDN "
             f"(and OIDN + TAA) on the same frames in the same process; learned = the step less its OIDN call; "
             f"check = the inference form against the plain fp32 model (eager, torch's ops, no native kernels).", "",
             "| model | output | render | form | frames | p50 ms | p95 ms | peak MB | step MB | learned ms | "
             "learned share | / OIDN | / OIDN + TAA | fp32 eager ms | check max abs | check PSNR dB |",
             "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in report["rows"]:
        check = row.get("check") or {}
        form = row.get("form") or "-"
        if "cuda_graph_captures" in row:  # 0: no structure could be captured, every step ran eagerly
            form += f" ({row['cuda_graph_captures']} captured)"
        lines.append(
            f"| {row['model']} | {row['output'][0]}x{row['output'][1]} | {row['render'][0]}x{row['render'][1]} | "
            f"{form} | {row['frames']} | {row['p50_ms']:.1f} | {row['p95_ms']:.1f} | "
            f"{row['peak_mb']:.0f} | {row['step_mb']:.0f} | {_cell(row.get('learned_p50_ms'), '.1f')} | "
            f"{_cell(row.get('learned_share'), '.0%')} | {_cell(row.get('ratio_to_oidn'), '.2f')} | "
            f"{_cell(row.get('ratio_to_oidn_taa'), '.2f')} | {_cell(row.get('eager_p50_ms'), '.1f')} | "
            f"{_cell(check.get('max_abs_diff'), '.2e')} | {_cell(check.get('min_psnr_db'), '.1f')} |")
    return "\n".join(lines) + "\n"


def ratio_figure(report: dict[str, Any]):
    """Bars of each learned model's time over its same-quality OIDN per output size (one panel per scale), the
    OIDN call inside the step and the learned part stacked; the line at 1 is OIDN itself."""
    from matplotlib.figure import Figure

    rows = [row for row in report["rows"] if row.get("ratio_to_oidn") is not None]
    if not rows:
        return None
    scales = sorted({row["scale"] for row in rows})
    figure = Figure(figsize=(6.5 * len(scales), 4.5))
    for panel, scale in enumerate(scales):
        axis = figure.add_subplot(1, len(scales), panel + 1)
        scaled = [row for row in rows if row["scale"] == scale]
        sizes = sorted({tuple(row["output"]) for row in scaled}, key=lambda size: size[0] * size[1])
        models = list(dict.fromkeys(row["model"] for row in scaled))
        width = 0.8 / len(models)
        for index, model in enumerate(models):
            by_size = {tuple(row["output"]): row for row in scaled if row["model"] == model}
            xs = [position + index * width for position, size in enumerate(sizes) if size in by_size]
            picked = [by_size[size] for size in sizes if size in by_size]
            oidn_ms = [row["p50_ms"] / row["ratio_to_oidn"] for row in picked]
            learned = [(row.get("learned_p50_ms") or 0.0) / ms for row, ms in zip(picked, oidn_ms)]
            total = [row["ratio_to_oidn"] for row in picked]
            bars = axis.bar(xs, [t - part for t, part in zip(total, learned)], width, label=f"{model}: OIDN call")
            axis.bar(xs, learned, width, bottom=[t - part for t, part in zip(total, learned)], hatch="//",
                     color=bars.patches[0].get_facecolor(), alpha=0.5, label=f"{model}: learned part")
        axis.axhline(1.0, color="black", linewidth=1)
        axis.set_xticks([position + 0.4 - width / 2 for position in range(len(sizes))],
                        [f"{w}x{h}" for w, h in sizes])
        axis.set_ylabel("p50 time / same-quality OIDN p50")
        axis.set_title(f"{scale}x output: fused step against OIDN" + (" + bicubic" if scale > 1 else ""))
        axis.legend(fontsize=6)
        axis.grid(True, axis="y", alpha=0.3)
    figure.suptitle(f"{report['device']['name']} ({report['device']['type']}, {report['device']['threads']} "
                    f"threads)", fontsize=9)
    figure.tight_layout()
    return figure
