"""The benchmark protocol (docs/evaluate.md): quality and speed of methods on whole sequences of a dataset split.

Every method is driven as in inference (``method.step`` frame by frame, history carried, inputs sanitized outside
the timed step) and scored per frame and per sequence; ``step`` alone is timed (``model.evaluation.timing``), with OIDN-high
timed in the same run for the ratios. What is measured and how, exactly: docs/evaluate.md.
"""

from __future__ import annotations

import os
import statistics
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from model.io.dataset import Dataset, Sequence
from model.deployment.inference_forms import FormTable, load_form_table, with_inference_forms
from model.methods.base import FrameBatch, Method
from model.evaluation.metrics import VDP_DISPLAY, VDP_FRAMES_PER_SECOND, FovVideoVdp, frame_metrics, temporal_error
from model.ops.tonemap import display_encode
from model.io.sanitize import SanitizeReport, sanitize_frame
from model.ops.output_bound import output_ratio
from model.evaluation.tables import cell, compact, source_label, table_row, table_rule
from model.evaluation.timing import median_ms, timed, torch_threads

# Methods whose network runs outside torch (OIDN's native library): torch counts none of their parameters or
# FLOPs, so tables say "-" (not counted) rather than 0, and the cost chart leaves them out.
UNCOUNTED_COST = ("oidn",)

FRAME_METRICS = ("psnr", "ssim", "flip", "smape")
SEQUENCE_METRICS = ("temporal_error", "fvvdp_jod")
METRICS = FRAME_METRICS + SEQUENCE_METRICS
TIMING_REFERENCE = "oidn:high"
WARMUP_FRAMES = 2
CHECKPOINT_SUFFIXES = (".pt", ".pth", ".ckpt")

Progress = Callable[[str], None]
LastOutputs = Callable[["EvaluationSequence", list[tuple[str, torch.Tensor]]], None]


@dataclass
class EvaluationSequence:
    """One sequence held in memory as single-frame batches with the reference at the evaluated scale."""

    name: str
    frames: list[FrameBatch]
    camera_cuts: list[bool]
    scale: int

    @classmethod
    def from_sequence(cls, sequence: Sequence, scale: int, frame_limit: int | None = None) -> EvaluationSequence:
        if scale not in sequence.scales:
            raise ValueError(_missing_scale_message(sequence, scale))
        count = len(sequence) if frame_limit is None else min(frame_limit, len(sequence))
        frames = [FrameBatch.from_bundles([sequence[index]], scale) for index in range(count)]
        # The dataset's name for it (its folder), unique in the dataset: a dataset that links sequences of others
        # may hold two whose own manifests give the same name (one scene rendered at two resolutions).
        return cls(sequence.path.name, frames, [bool(f.camera_cut[0]) for f in frames], scale)

    @property
    def input_resolution(self) -> str:
        return f"{self.frames[0].width}x{self.frames[0].height}"

    @property
    def output_resolution(self) -> str:
        return f"{self.frames[0].width * self.scale}x{self.frames[0].height * self.scale}"


def _missing_scale_message(sequence: Sequence, scale: int) -> str:
    present = ", ".join(str(s) for s in sequence.scales) or "none"
    return (f"sequence '{sequence.name}' ({sequence.path}) has no references at scale {scale} "
            f"(scales present: {present})")


# ------------------------------------------------------------------------------------------- methods

def resolve_method(text: str, scale: int) -> tuple[Method, str]:
    """``NAME[:PRESET]`` from the registry, a checkpoint file of a trained method, or the name of a pretrained model
    (``model.deployment.pretrained``); returns (method, source).

    A text naming an existing file is a checkpoint (loaded with ``model.training.checkpoint.load_method``); a text that
    looks like a path but names no file is reported as a missing checkpoint rather than an unknown method.
    """
    path = Path(text)
    if path.is_file():
        from model.training.checkpoint import load_method

        return load_method(path, scale=scale), str(path)
    from model.deployment.pretrained import is_pretrained

    if is_pretrained(text):  # a model shipped in pretrained/ (sha256 checked when loaded)
        from model.deployment.pretrained import load_pretrained

        return load_pretrained(text, scale=scale), f"pretrained:{text}"
    if path.suffix in CHECKPOINT_SUFFIXES or os.sep in text:
        raise FileNotFoundError(f"checkpoint {text} not found")
    from model.methods.registry import build_method

    return build_method(text, scale), text


def _prepare(method: Method | str, scale: int) -> tuple[Method, str]:
    """The method in its inference form (what sessions run), with where it came from."""
    if isinstance(method, Method):
        if method.scale != scale:
            raise ValueError(f"method {method.label} outputs scale {method.scale}, evaluation is at scale {scale}")
        return method.for_inference(), method.label
    method, source = resolve_method(method, scale)
    return method.for_inference(), source


def method_description(method: Method, source: str) -> dict:
    """Label, where it came from, parameter count and FLOPs per output pixel (counted on the CPU)."""
    from model.methods.registry import flops_per_pixel

    return {"label": method.label, "source": source, "method": method.name, "preset": method.preset,
            "scale": method.scale, "learned": bool(method.learned), "params": method.parameter_count(),
            "flops_per_pixel": float(flops_per_pixel(method))}


# ---------------------------------------------------------------------------------------- one sequence

def run_sequence(method: Method, sequence: EvaluationSequence, *, vdp: FovVideoVdp | None = None,
                 with_metrics: bool = True, warmup_frames: int = WARMUP_FRAMES,
                 device: torch.device | str = "cpu", keep_outputs: bool = False, keep_last: bool = False) -> dict:
    """Step ``method`` through ``sequence``: step times of the frames after warm-up, and (``with_metrics``)
    per-sequence means of the frame metrics, the temporal error and, when ``vdp`` is given, the JOD.

    Every input frame goes through ``sanitize_frame`` first (not timed). Returns {"frames", "step_seconds": [...],
    "sanitized": the repaired-pixel counts (``SanitizeReport.to_dict``), "keeps_history": whether any step
    returned a non-empty state (a temporal method; per-frame methods return ``{}``), with metrics "metrics":
    {name: value or None}, "per_frame": {frame metric: [value per frame]} and "output_ratio" (the largest
    brightest-output / brightest-input ratio of any frame), and with ``keep_outputs`` (which needs the metrics)
    "outputs": the linear outputs as one (T, C, H, W) CPU tensor, with ``keep_last`` (also with the metrics) "last_output": the last frame's linear (1, C, H, W) CPU output}.
    """
    if keep_outputs and not with_metrics:
        raise ValueError("keep_outputs needs with_metrics: outputs are checked and copied with the metrics")
    device = torch.device(device)
    method.eval()
    state = None
    step_seconds: list[float] = []
    frame_values: dict[str, list[float]] = {name: [] for name in FRAME_METRICS}
    outputs_ldr: list[torch.Tensor] = []
    references_ldr: list[torch.Tensor] = []
    kept: list[torch.Tensor] = []
    keeps_history = False
    output_peak_ratio = 0.0  # the worst frame's brightest output over its brightest input
    sanitized = SanitizeReport()
    with torch.inference_mode():
        for index, frame in enumerate(sequence.frames):
            inputs, repaired = sanitize_frame(frame.without_reference().to(device))
            sanitized = sanitized + repaired
            (output, state), seconds = timed(lambda: method.step(inputs, state), device)
            if index >= warmup_frames:
                step_seconds.append(seconds)
            keeps_history = keeps_history or bool(state)
            if not with_metrics:
                continue
            output = _checked_output(output, frame, method, sequence, index).cpu()
            output_peak_ratio = max(output_peak_ratio, output_ratio(output, inputs.color.cpu()))
            for name, values in frame_metrics(output, frame.reference).items():
                frame_values[name].append(float(values[0]))
            outputs_ldr.append(display_encode(output[0]))
            references_ldr.append(display_encode(frame.reference[0]))
            if keep_outputs:
                kept.append(output[0])
            if keep_last:
                last = output

    result: dict = {"frames": len(sequence.frames), "step_seconds": step_seconds, "sanitized": sanitized.to_dict(),
                    "keeps_history": keeps_history}
    if keep_outputs:
        result["outputs"] = torch.stack(kept)
    if keep_last and with_metrics:
        result["last_output"] = last
    if with_metrics:
        result["per_frame"] = frame_values
        result["output_ratio"] = output_peak_ratio
        metrics: dict[str, float | None] = {name: statistics.fmean(v) for name, v in frame_values.items()}
        outputs, references = torch.stack(outputs_ldr), torch.stack(references_ldr)
        # On display-encoded frames, as the other LDR metrics: flicker in the dark counts as the eye sees it,
        # and one firefly's HDR value cannot dominate the mean.
        metrics["temporal_error"] = temporal_error(outputs, references, sequence.camera_cuts)
        metrics["fvvdp_jod"] = None
        if vdp is not None:
            try:
                metrics["fvvdp_jod"] = vdp.jod(outputs, references)
            except RuntimeError as error:
                result["fvvdp_error"] = str(error)
        result["metrics"] = metrics
    return result


def _checked_output(output: torch.Tensor, frame: FrameBatch, method: Method, sequence: EvaluationSequence,
                    index: int) -> torch.Tensor:
    where = f"{method.label} on sequence '{sequence.name}', frame {index}"
    if tuple(output.shape) != tuple(frame.reference.shape):
        raise ValueError(f"{where}: output shape {tuple(output.shape)} differs from the reference's "
                         f"{tuple(frame.reference.shape)}")
    if not bool(torch.isfinite(output).all()):
        raise RuntimeError(f"{where}: output is not finite (NaN or Inf) for a finite input")
    return output


# ----------------------------------------------------------------------------------------- summaries

def _mean_or_none(values: Iterable[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    return statistics.fmean(present) if present else None


def _ratio(ms: float | None, reference_ms: float | None) -> float | None:
    if ms is None or reference_ms is None or reference_ms <= 0:
        return None
    return ms / reference_ms


def _timing(step_seconds: list[float], sequences: list[EvaluationSequence], warmup_frames: int,
            device: torch.device) -> dict:
    return {"ms_per_frame": median_ms(step_seconds), "frames_timed": len(step_seconds),
            "warmup_frames_per_sequence": warmup_frames,
            "input_resolutions": sorted({s.input_resolution for s in sequences}),
            "output_resolutions": sorted({s.output_resolution for s in sequences}),
            "threads": torch.get_num_threads(), "device": str(device)}


def summarize_method(description: dict, runs: dict[str, dict], sequences: list[EvaluationSequence],
                     warmup_frames: int, device: torch.device, reference_ms: float | None) -> dict:
    """One method's report entry from its per-sequence runs (sequence name -> ``run_sequence`` result)."""
    step_seconds = [s for run in runs.values() for s in run["step_seconds"]]
    timing = _timing(step_seconds, sequences, warmup_frames, device)
    per_sequence = {name: {"frames": run["frames"], **run["metrics"]} for name, run in runs.items()}
    means = {name: _mean_or_none(entry[name] for entry in per_sequence.values()) for name in METRICS}
    return {**description, "metrics": means, "sequences": per_sequence, "timing": timing,
            "ms_per_frame": timing["ms_per_frame"], "time_ratio_to_oidn": _ratio(timing["ms_per_frame"], reference_ms)}


def evaluate_method(method: Method | str, sequences: list[EvaluationSequence], scale: int = 1, *,
                    vdp: bool | FovVideoVdp = True, warmup_frames: int = WARMUP_FRAMES,
                    device: torch.device | str = "cpu", reference_ms: float | None = None) -> dict:
    """Evaluate one method on sequences already in memory; ``reference_ms`` (OIDN's) gives the time ratio."""
    method, source = _prepare(method, scale)
    description = method_description(method, source)
    device = torch.device(device)
    method.to(device)
    metric = FovVideoVdp(device) if vdp is True else (vdp or None)
    if metric is not None and not metric.available:
        metric = None
    runs = {s.name: run_sequence(method, s, vdp=metric, warmup_frames=warmup_frames, device=device)
            for s in sequences}
    return summarize_method(description, runs, sequences, warmup_frames, device, reference_ms)


# ------------------------------------------------------------------------------------------ a dataset

def load_split(dataset_dir: str | os.PathLike, split: str, scale: int) -> list[Sequence]:
    """The split's sequences, checked to hold references at ``scale`` (reads manifests only)."""
    dataset = Dataset(dataset_dir)
    names = dataset.names(split)
    if not names:
        summary = {s: entry["sequences"] for s, entry in dataset.summary().items() if entry["sequences"]}
        present = ", ".join(f"{s} ({n})" for s, n in summary.items()) or "none"
        raise ValueError(f"dataset {dataset.root} has no sequences in split '{split}' (splits present: {present})")
    sequences = dataset.sequences(split)
    missing = [s for s in sequences if scale not in s.scales]
    if missing:
        raise ValueError(_missing_scale_message(missing[0], scale)
                         + (f"; {len(missing) - 1} more sequences lack it too" if len(missing) > 1 else ""))
    return sequences


def evaluate(dataset_dir: str | os.PathLike, methods: list[Method | str], split: str = "test", scale: int = 1, *,
             frame_limit: int | None = None, threads: int | None = None, vdp: bool = True,
             timing_reference: Method | str | None = TIMING_REFERENCE, warmup_frames: int = WARMUP_FRAMES,
             device: torch.device | str = "cpu", progress: Progress | None = None,
             inference_forms: FormTable | str | None = "measured", last_outputs: LastOutputs | None = None) -> dict:
    """Run the benchmark protocol for ``methods`` on one split of a dataset; returns a JSON-serializable report.

    ``methods`` are ``NAME[:PRESET]`` texts, checkpoint paths, or Method objects. ``timing_reference`` (OIDN-high
    by default) is timed on the same frames in the same run; None skips it and leaves the ratios None. When it is
    also among ``methods`` its evaluated run is the timing. ``frame_limit`` keeps the first frames of every
    sequence; ``threads`` sets torch's thread count for the run (restored afterwards); ``vdp=False`` skips
    FovVideoVDP, the slowest metric. Learned methods' networks run in the form ``inference_forms`` measured for
    the frames' resolution, as sessions run them (``model.deployment.inference_forms``; "off": fp32 eager).
    ``last_outputs`` is called once per sequence, after every method ran on it, with the sequence and each
    method's (label, output) of its last frame (``model.evaluation.compare.last_frame_panels`` draws them).
    """
    if not methods:
        raise ValueError("no methods to evaluate")
    forms = load_form_table(inference_forms)
    if frame_limit is not None and frame_limit < 1:
        raise ValueError(f"frame limit must be positive, got {frame_limit}")
    if threads is not None and threads < 1:
        raise ValueError(f"thread count must be positive, got {threads}")
    say = progress or (lambda message: None)
    device = torch.device(device)
    # Everything that can be wrong with the input is found before any frame is read.
    folders = load_split(dataset_dir, split, scale)
    entrants = [_Entrant(*_prepare(m, scale)) for m in methods]
    reference = _timing_reference(timing_reference, entrants, scale)
    runners = entrants + ([reference] if reference is not None and reference.timing_only else [])

    with torch_threads(threads):
        descriptions = [method_description(e.method, e.source) for e in entrants]
        for entrant in runners:  # after the FLOP count, which copies the method as for_inference() left it
            with_inference_forms(entrant.method, forms, device)
        for entrant in runners:
            entrant.method.to(device)
        metric = FovVideoVdp(device) if vdp else None
        usable_metric = metric if metric is not None and metric.available else None
        sequences: list[EvaluationSequence] = []
        for folder in folders:
            # One sequence in memory at a time; every method runs on it before the next one is read.
            sequence = EvaluationSequence.from_sequence(folder, scale, frame_limit)
            sequences.append(sequence)
            for entrant in runners:
                what = " (timing only)" if entrant.timing_only else ""
                say(f"{entrant.method.label}{what}: sequence {sequence.name} ({len(sequence.frames)} frames)")
                entrant.runs[sequence.name] = run_sequence(
                    entrant.method, sequence, vdp=usable_metric, with_metrics=not entrant.timing_only,
                    warmup_frames=warmup_frames, device=device, keep_last=last_outputs is not None)
            if last_outputs is not None:
                last_outputs(sequence, [(e.method.label, e.runs[sequence.name].pop("last_output")) for e in entrants])
        reference_seconds = reference.step_seconds if reference is not None else []
        reference_ms = median_ms(reference_seconds)
        return {
            "dataset": str(Path(dataset_dir)),
            "split": split,
            "scale": scale,
            "frame_limit": frame_limit,
            "device": str(device),
            "threads": torch.get_num_threads(),
            "torch_version": torch.__version__,
            "warmup_frames_per_sequence": warmup_frames,
            "sequences": [{"name": s.name, "frames": len(s.frames), "input_resolution": s.input_resolution,
                           "output_resolution": s.output_resolution, "camera_cuts": sum(s.camera_cuts[1:])}
                          for s in sequences],
            "timing_reference": None if reference is None else {
                "label": reference.method.label, "ms_per_frame": reference_ms,
                "timing": _timing(reference_seconds, sequences, warmup_frames, device)},
            "fvvdp": _vdp_section(metric, entrants),
            # The same for every method (the inputs are): counts from the first method's runs.
            "sanitized_inputs": {s.name: runners[0].runs[s.name]["sanitized"] for s in sequences},
            "methods": [summarize_method(description, e.runs, sequences, warmup_frames, device, reference_ms)
                        for description, e in zip(descriptions, entrants)],
        }


@dataclass
class _Entrant:
    """A method in one evaluation run, with its per-sequence results; ``timing_only`` skips the metrics."""

    method: Method
    source: str
    timing_only: bool = False
    runs: dict[str, dict] = field(default_factory=dict)

    @property
    def step_seconds(self) -> list[float]:
        return [seconds for run in self.runs.values() for seconds in run["step_seconds"]]


def _timing_reference(reference: Method | str | None, entrants: list[_Entrant], scale: int) -> _Entrant | None:
    """The evaluated entrant that is the timing reference, or a timing-only one, or None."""
    if reference is None:
        return None
    label = reference.label if isinstance(reference, Method) else reference
    for entrant in entrants:
        if label in (entrant.method.label, entrant.source):
            return entrant
    if isinstance(reference, Method):
        return _Entrant(reference, label, timing_only=True)
    # The reference is timed at the evaluated scale when it supports it, else at scale 1 on the same frames:
    # OIDN denoises at render resolution, so its time is a cost per input frame either way.
    try:
        try:
            method, _ = resolve_method(reference, scale)
        except ValueError:
            method, _ = resolve_method(reference, 1)
    except KeyError as error:
        message = error.args[0] if error.args else error
        raise KeyError(f"cannot build the timing reference {label!r}: {message}; "
                       f"evaluate without it (timing_reference=None, CLI --no-oidn)") from None
    return _Entrant(method, reference, timing_only=True)


def _vdp_section(metric: FovVideoVdp | None, entrants: list[_Entrant]) -> dict:
    failures = [{"method": e.method.label, "sequence": name, "reason": run["fvvdp_error"]}
                for e in entrants for name, run in e.runs.items() if "fvvdp_error" in run]
    return {"enabled": metric is not None, "available": bool(metric is not None and metric.available),
            "reason": None if metric is None else metric.unavailable_reason,
            "display": VDP_DISPLAY, "frames_per_second": VDP_FRAMES_PER_SECOND, "failures": failures}


# -------------------------------------------------------------------------------------------- table

# How each measure appears in tables: key -> (header, format).
COLUMNS = {
    "psnr": ("PSNR dB ↑", "{:.2f}"),
    "ssim": ("SSIM ↑", "{:.4f}"),
    "flip": ("FLIP ↓", "{:.4f}"),
    "smape": ("SMAPE ↓", "{:.4f}"),
    "temporal_error": ("temporal ↓", "{:.5f}"),
    "fvvdp_jod": ("JOD ↑", "{:.2f}"),
    "ms_per_frame": ("ms/frame", "{:.3g}"),
    "time_ratio_to_oidn": ("time / OIDN", "{:.3g}x"),
}


def run_summary(report: dict) -> dict:
    """What an evaluation report's run covered, for captions: "sequences" and "frames" (counts), "inputs" and
    "outputs" (resolutions), "reference" (the timing reference's label and time, None without one)."""
    sequences = report["sequences"]
    reference = report.get("timing_reference")
    return {"sequences": len(sequences), "frames": sum(s["frames"] for s in sequences),
            "inputs": ", ".join(sorted({s["input_resolution"] for s in sequences})),
            "outputs": ", ".join(sorted({s["output_resolution"] for s in sequences})),
            "reference": (f"{reference['label']} {cell(reference['ms_per_frame'], '{:.3g}')} ms/frame"
                          if reference else None)}


def format_table(report: dict) -> str:
    """The report as a Markdown table, one row per method, with a line stating what was measured and how."""
    run = run_summary(report)
    caption = (f"{report['split']} split of {report['dataset']}: {run['sequences']} sequences, {run['frames']} "
               f"frames, input {run['inputs']} -> output {run['outputs']} (scale {report['scale']}); time per frame "
               f"= median after {report['warmup_frames_per_sequence']} warm-up frames per sequence, "
               f"{report['threads']} threads, {report['device']}; {run['reference'] or 'no timing reference'}")
    repaired = {name: counts["total"] for name, counts in report.get("sanitized_inputs", {}).items()
                if counts["total"]}
    if repaired:
        caption += "; inputs sanitized (NaN/Inf or out of range, pixels): " + ", ".join(
            f"{name} {total}" for name, total in repaired.items())
    if not report["fvvdp"]["enabled"]:
        caption += "; FovVideoVDP skipped"
    elif not report["fvvdp"]["available"]:
        caption += f"; FovVideoVDP unavailable: {report['fvvdp']['reason']}"
    columns = [*METRICS, "ms_per_frame", "time_ratio_to_oidn"]
    header = ["method", "params", "FLOPs/px"] + [COLUMNS[key][0] for key in columns]
    lines = [caption, "", table_row(header), table_rule("l" + "r" * (len(header) - 1))]
    labels = [entry["label"] for entry in report["methods"]]
    for entry in report["methods"]:
        ratio = entry["time_ratio_to_oidn"]
        counted = entry.get("method") not in UNCOUNTED_COST
        name = source_label(entry["label"], entry.get("source"), labels)
        cells = [name] + ([compact(entry["params"]), compact(entry["flops_per_pixel"])] if counted
                                    else ["-", "-"])
        values = {**entry["metrics"], "ms_per_frame": entry["ms_per_frame"], "time_ratio_to_oidn": ratio}
        cells += [cell(values[key], COLUMNS[key][1]) for key in columns]
        lines.append(table_row(cells))
    return "\n".join(lines)
