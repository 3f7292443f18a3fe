"""Right-sizing: the smallest preset of a method family that meets a target, chosen from a ladder of trained sizes.

A *ladder* is the family's presets ordered by FLOPs per output pixel of their inference form
(``model.methods.registry.inference_cost``, smallest first; ties by parameter count). Each preset on it is
obtained (trained, or reused, see below), measured on the validation split (PSNR, SSIM, FLIP through
``model.evaluate``, the method in its inference form, driven frame by frame with its history) and timed (ms
per frame, below), and the target picks one:

    psnr=X          validation PSNR >= X dB                   -> the smallest preset that meets it
    flip=X          validation FLIP <= X                      -> the smallest preset that meets it
    ms=X[@WxH]      ms per frame <= X at render size WxH      -> the best validation PSNR among the presets within
                                                                 the budget (ties: the smaller)
    within=D        validation PSNR >= PSNR of the largest preset - D dB -> the smallest preset that meets it

Timing: ``method.step`` of the preset's architecture in its inference form (``for_inference``) on synthetic frames
of the stated render resolution (``registry.example_batch``), its history carried, under
``torch.inference_mode``, median of ``timing_frames`` frames after ``timing_warmup`` warm-up frames, with the
stated torch thread count and device. Speed does not depend on the weights, so every preset is timed *before*
any training, which is cheap and lets the ladder stop early:

- psnr / flip: presets are obtained and measured from the smallest up; the first that meets the target ends the
  ladder (a larger preset could only be a larger choice); the larger ones are reported as not needed.
- ms: presets over the budget are never trained; every preset within it is (quality decides among them).
- within: the largest preset is obtained first (its PSNR sets the bar), then presets from the smallest up to the
  first that clears the bar.

Reuse (``obtain``): a preset trained before with the same training settings on the same data is not trained
again. The *fit key* (``training_key``) hashes every training setting that changes the weights (family, scale,
splits, crop, frames per sample, batch, steps, learning rate and schedule, loss settings, seed) with a
fingerprint of the data (the dataset and sequence manifests of the train and validation splits); presets train
into ``OUT/<preset>-<key>/``. In order:

1. a checkpoint in the fit's own output folder: ``OUT/<preset>-<key>/last.pt`` at the final step is reused as it
   is; one short of it is resumed (``model.train``'s exact resume);
2. a registered model version tagged with the same ``fit_key``, method, preset and scale (``ModelStore``): its
   checkpoint is downloaded and measured again;
3. otherwise the preset is trained.

This module is pure PyTorch: MLflow comes in through two small protocols, ``LadderTracker`` (the parent run: the
ladder's params, metrics and files) and ``ModelStore`` (finding, registering, tagging and aliasing model
versions), implemented in ``workers.tasks.fit``. ``run_ladder`` is the choice alone and takes plain callables
(time, obtain, measure), so its rules are tested with fake measurements.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch
from model.evaluate import torch_threads

TARGET_KINDS = ("psnr", "flip", "ms", "within")
DEFAULT_TIMING_RESOLUTION = (256, 256)  # (width, height) of the render frames timed when the target is not ms
DEFAULT_ALIAS = "fitted"
TIMING_FRAMES = 10
TIMING_WARMUP = 3
LADDER_JSON = "ladder.json"
LADDER_MARKDOWN = "ladder.md"
# Settings that do not change the trained weights (or are the preset itself) stay out of the fit key.
KEY_EXCLUDED = ("method", "data", "out", "resume", "device", "world_size", "checkpoint_every", "validate_every",
                "validation_frames", "num_threads", "tracking_uri", "experiment", "register_as")
ALIAS_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]{0,254}$")

Progress = Callable[[int, int, str], None]  # (current, total, message), as model.train's
Say = Callable[[str], None]

# Rung statuses
TRAINED, RESUMED, REUSED_CHECKPOINT, REUSED_REGISTRY, SKIPPED = (
    "trained", "resumed", "reused-checkpoint", "reused-registry", "skipped")


# ------------------------------------------------------------------------------------------------ target

@dataclass(frozen=True)
class Target:
    """What the chosen preset must achieve (see the module notes); ``resolution`` (width, height) for ms."""

    kind: str
    value: float
    resolution: tuple[int, int] | None = None

    @classmethod
    def parse(cls, text: str, default_resolution: tuple[int, int] = DEFAULT_TIMING_RESOLUTION) -> Target:
        """``psnr=30``, ``flip=0.12``, ``ms=20@128x128`` (``ms=20``: at ``default_resolution``), ``within=0.2``."""
        forms = "psnr=DB, flip=ERROR, ms=MILLISECONDS[@WIDTHxHEIGHT] or within=DB"
        kind, sep, rest = str(text).strip().partition("=")
        kind = kind.strip().lower()
        if not sep or kind not in TARGET_KINDS:
            raise ValueError(f"target {text!r} is not one of {forms}")
        number, at, size = rest.partition("@")
        if at and kind != "ms":
            raise ValueError(f"target {text!r}: only an ms target takes @WIDTHxHEIGHT")
        try:
            value = float(number)
        except ValueError:
            raise ValueError(f"target {text!r}: {number.strip()!r} is not a number ({forms})") from None
        if not math.isfinite(value):
            raise ValueError(f"target {text!r}: the value must be finite")
        if kind in ("ms", "flip") and value <= 0:
            raise ValueError(f"target {text!r}: {kind} must be positive")
        if kind == "within" and value < 0:
            raise ValueError(f"target {text!r}: within takes a PSNR margin >= 0 dB")
        resolution = None
        if kind == "ms":
            resolution = parse_resolution(size) if at else tuple(default_resolution)
        return cls(kind, value, resolution)

    def __str__(self) -> str:
        value = f"{self.value:g}"
        if self.kind == "ms":
            return f"ms={value}@{self.resolution[0]}x{self.resolution[1]}"
        return f"{self.kind}={value}"

    def describe(self, bar: float | None = None) -> str:
        """In words, e.g. 'validation PSNR >= 30 dB'."""
        if self.kind == "psnr":
            return f"validation PSNR >= {self.value:g} dB"
        if self.kind == "flip":
            return f"validation FLIP <= {self.value:g}"
        if self.kind == "ms":
            return (f"<= {self.value:g} ms per frame at {self.resolution[0]}x{self.resolution[1]} (render), then "
                    f"the best validation PSNR")
        text = f"validation PSNR within {self.value:g} dB of the largest preset"
        return text + (f" (>= {bar:.2f} dB)" if bar is not None else "")

    def quality_met(self, rung: Rung, bar: float | None = None) -> bool | None:
        """Whether a measured rung meets a quality target (psnr, flip, within with its ``bar``); None: unknown."""
        if self.kind == "psnr":
            return None if rung.psnr is None else rung.psnr >= self.value
        if self.kind == "flip":
            return None if rung.flip is None else rung.flip <= self.value
        if self.kind == "within":
            return None if rung.psnr is None or bar is None else rung.psnr >= bar - 1e-9
        return None

    def within_budget(self, rung: Rung) -> bool | None:
        if self.kind != "ms":
            return None
        return None if rung.ms_per_frame is None else rung.ms_per_frame <= self.value


def parse_resolution(text: str) -> tuple[int, int]:
    """'128x128' or '128' -> (width, height)."""
    parts = str(text).strip().lower().split("x")
    try:
        values = [int(part) for part in parts]
    except ValueError:
        raise ValueError(f"resolution {text!r} is not WIDTHxHEIGHT (e.g. 128x128)") from None
    if len(values) == 1:
        values *= 2
    if len(values) != 2 or min(values) < 1 or max(values) > 8192:
        raise ValueError(f"resolution {text!r} is not WIDTHxHEIGHT with sides between 1 and 8192")
    return values[0], values[1]


# ------------------------------------------------------------------------------------------------ ladder

@dataclass(frozen=True)
class Candidate:
    """One preset of the family, with the cost that orders the ladder."""

    preset: str
    flops_per_pixel: float
    params: int


@dataclass
class Obtained:
    """A preset's weights, wherever they came from: ``status`` is trained, resumed, reused-checkpoint or
    reused-registry; ``registered`` the model version holding them ({name, version, ...}), if any."""

    checkpoint: Path | str | None
    status: str
    registered: dict[str, Any] | None = None
    seconds: float = 0.0
    detail: str | None = None


@dataclass
class Measurement:
    psnr: float | None
    flip: float | None
    ssim: float | None = None
    extra: dict[str, float | None] = field(default_factory=dict)


@dataclass
class Rung:
    """One preset on the ladder and what became of it."""

    preset: str
    flops_per_pixel: float
    params: int
    ms_per_frame: float | None = None
    status: str = SKIPPED
    note: str | None = None  # why it was skipped, or where its weights came from
    psnr: float | None = None
    ssim: float | None = None
    flip: float | None = None
    meets: bool | None = None  # the target (for ms: within the budget); None when not measured
    checkpoint: str | None = None
    registered: dict[str, Any] | None = None
    seconds: float = 0.0  # obtaining (training) time
    chosen: bool = False

    @property
    def measured(self) -> bool:
        return self.status != SKIPPED

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class LadderResult:
    family: str
    scale: int
    target: Target
    rungs: list[Rung]
    chosen: Rung | None
    reason: str
    bar: float | None = None  # within: the PSNR the chosen preset had to reach
    info: dict[str, Any] = field(default_factory=dict)  # timing set-up, dataset, fit key, registration, ...

    @property
    def met(self) -> bool:
        return self.chosen is not None

    def to_dict(self) -> dict[str, Any]:
        return {"family": self.family, "scale": self.scale, "target": str(self.target),
                "target_description": self.target.describe(self.bar), "met": self.met,
                "chosen": None if self.chosen is None else self.chosen.preset, "reason": self.reason,
                "bar": self.bar, **self.info, "ladder": [rung.to_dict() for rung in self.rungs]}


class LadderTracker(Protocol):
    """Where the ladder is recorded (one parent run); ``workers.tasks.fit.MLflowFit`` implements it."""

    def log_params(self, params: dict[str, Any]) -> None: ...

    def log_metrics(self, metrics: dict[str, float], step: int) -> None: ...

    def log_text(self, name: str, text: str) -> None:
        """A text file (``ladder.json``, ``ladder.md``) stored with the run."""


def order_ladder(candidates: list[Candidate]) -> list[Candidate]:
    """Smallest first: by FLOPs per pixel, then parameters (a stable sort keeps the registry's order on ties)."""
    return sorted(candidates, key=lambda c: (c.flops_per_pixel, c.params))


class _LadderProgress:
    """Progress over the whole ladder from each preset's own (current, total) reports: the units of the preset
    being obtained (training steps), with the presets still to come assumed to cost as much."""

    def __init__(self, report: Progress | None, planned: int) -> None:
        self.report = report
        self.planned = planned  # presets that may still be obtained, the current one included
        self.done = 0
        self.unit = 1

    def total(self, current_units: int = 0) -> int:
        return self.done + max(self.unit, current_units) * max(self.planned, 1)

    def callback(self, preset: str) -> Progress:
        def step(current: int, total: int, message: str) -> None:
            self.unit = max(1, int(total))
            if self.report is not None:
                self.report(self.done + int(current), self.total(), f"{preset}: {message}")
        return step

    def say(self, message: str) -> None:
        if self.report is not None:
            self.report(self.done, self.total(), message)

    def finished_one(self) -> None:
        self.done += self.unit
        self.planned = max(0, self.planned - 1)

    def end(self, message: str) -> None:
        self.planned = 0
        if self.report is not None:
            self.report(self.done, max(self.done, 1), message)


def run_ladder(candidates: list[Candidate], target: Target, *, family: str = "", scale: int = 1,
               time_preset: Callable[[str], float],
               obtain: Callable[[str, Progress], Obtained],
               measure: Callable[[str, Obtained], Measurement],
               tracker: LadderTracker | None = None, progress: Progress | None = None,
               say: Say | None = None, resolution: tuple[int, int] | None = None) -> LadderResult:
    """Time every preset, obtain and measure the ones the target needs, and choose (see the module notes).

    ``time_preset(preset)`` -> ms per frame; ``obtain(preset, progress)`` -> Obtained (trains or reuses);
    ``measure(preset, obtained)`` -> Measurement on the validation split. Returns the ladder with the choice
    (``chosen`` None when no preset meets the target). Logs per-preset params and metrics to ``tracker``.
    ``resolution`` (width, height) is the timing resolution, for the messages (an ms target names its own).
    """
    if not candidates:
        raise ValueError("the ladder has no presets")
    say = say or (lambda message: None)
    rungs = [Rung(c.preset, c.flops_per_pixel, c.params) for c in order_ladder(candidates)]
    by_preset = {rung.preset: rung for rung in rungs}
    if len(by_preset) != len(rungs):
        raise ValueError("a preset appears twice on the ladder")

    timed_at = target.resolution or resolution
    for rung in rungs:
        say(f"timing {rung.preset}" + (f" at {timed_at[0]}x{timed_at[1]}" if timed_at else ""))
        rung.ms_per_frame = float(time_preset(rung.preset))
        if target.kind == "ms":
            rung.meets = target.within_budget(rung)

    if target.kind == "ms":
        order = [rung for rung in rungs if rung.meets]
        for rung in rungs:
            if not rung.meets:
                rung.note = (f"over the time budget: {rung.ms_per_frame:.3g} ms > {target.value:g} ms per frame at "
                             f"{_resolution_text(target)}; not trained")
    elif target.kind == "within":
        order = [rungs[-1]] + rungs[:-1]
    else:
        order = list(rungs)

    ladder_progress = _LadderProgress(progress, len(order))
    bar: float | None = None
    chosen: Rung | None = None
    for rung in order:
        _obtain_and_measure(rung, obtain, measure, ladder_progress, say)
        _log_rung(tracker, rung, rungs.index(rung))
        if target.kind == "within" and bar is None:
            if rung.psnr is None:
                raise RuntimeError(f"preset {rung.preset} has no validation PSNR; the within target needs it")
            bar = rung.psnr - target.value
            rung.meets = True  # the largest always clears its own bar
            continue  # it sets the bar; now from the smallest up
        if target.kind == "ms":
            continue  # every preset within the budget is measured; quality decides after
        rung.meets = target.quality_met(rung, bar)
        if rung.meets:
            chosen = rung
            break
    if target.kind == "within" and chosen is None and bar is not None:
        chosen = rungs[-1]  # no smaller preset came within the margin

    if target.kind == "ms":
        within = [rung for rung in rungs if rung.meets and rung.psnr is not None]
        if within:
            best = max(rung.psnr for rung in within)
            chosen = next(rung for rung in within if rung.psnr == best)  # ladder order: the smallest on a tie
    _mark_not_needed(rungs, chosen, target)
    reason = _reason(rungs, chosen, target, bar)
    if chosen is not None:
        chosen.chosen = True
    ladder_progress.end(reason)
    say(reason)
    return LadderResult(family=family, scale=scale, target=target, rungs=rungs, chosen=chosen, reason=reason,
                        bar=bar)


def _obtain_and_measure(rung: Rung, obtain, measure, ladder_progress: _LadderProgress, say: Say) -> None:
    say(f"obtaining {rung.preset} (train or reuse)")
    obtained = obtain(rung.preset, ladder_progress.callback(rung.preset))
    rung.status = obtained.status
    rung.note = obtained.detail
    rung.checkpoint = None if obtained.checkpoint is None else str(obtained.checkpoint)
    rung.registered = obtained.registered
    rung.seconds = obtained.seconds
    ladder_progress.finished_one()  # its units are the training steps; measuring counts none
    ladder_progress.say(f"measuring {rung.preset} on the validation split")
    say(f"measuring {rung.preset} on the validation split")
    measured = measure(rung.preset, obtained)
    rung.psnr, rung.flip, rung.ssim = measured.psnr, measured.flip, measured.ssim


def _mark_not_needed(rungs: list[Rung], chosen: Rung | None, target: Target) -> None:
    for rung in rungs:
        if rung.measured or rung.note:
            continue
        if chosen is not None:
            rung.note = f"not needed: {chosen.preset} already meets {target}; not trained"
        else:
            rung.note = "not trained"


def _reason(rungs: list[Rung], chosen: Rung | None, target: Target, bar: float | None) -> str:
    if target.kind == "ms":
        within = [rung for rung in rungs if rung.meets]
        if chosen is None:
            fastest = min(rungs, key=lambda r: r.ms_per_frame if r.ms_per_frame is not None else math.inf)
            return (f"no preset runs within {target.value:g} ms per frame at {_resolution_text(target)}; the "
                    f"fastest, {fastest.preset}, takes {fastest.ms_per_frame:.3g} ms")
        return (f"{chosen.preset}: the best validation PSNR ({chosen.psnr:.2f} dB) of the {len(within)} preset(s) "
                f"within {target.value:g} ms per frame at {_resolution_text(target)} "
                f"({chosen.ms_per_frame:.3g} ms)")
    if chosen is None:
        measured = [rung for rung in rungs if rung.measured]
        if target.kind == "flip":
            best = min(measured, key=lambda r: r.flip if r.flip is not None else math.inf)
            return f"no preset meets {target.describe()}; the best, {best.preset}, has FLIP {best.flip:.4f}"
        best = max(measured, key=lambda r: r.psnr if r.psnr is not None else -math.inf)
        return f"no preset meets {target.describe(bar)}; the best, {best.preset}, has {best.psnr:.2f} dB"
    if target.kind == "flip":
        return f"{chosen.preset}: the smallest preset with {target.describe()} (FLIP {chosen.flip:.4f})"
    return f"{chosen.preset}: the smallest preset with {target.describe(bar)} ({chosen.psnr:.2f} dB)"


def _resolution_text(target: Target) -> str:
    if target.resolution is None:
        return "the timing resolution"
    return f"{target.resolution[0]}x{target.resolution[1]}"


def _log_rung(tracker: LadderTracker | None, rung: Rung, position: int) -> None:
    if tracker is None:
        return
    tracker.log_params({f"{rung.preset}.status": rung.status, f"{rung.preset}.params": rung.params,
                        f"{rung.preset}.flops_per_pixel": rung.flops_per_pixel,
                        f"{rung.preset}.checkpoint": rung.checkpoint or ""})
    values = {"psnr": rung.psnr, "ssim": rung.ssim, "flip": rung.flip, "ms_per_frame": rung.ms_per_frame,
              "flops_per_pixel": rung.flops_per_pixel, "params": float(rung.params),
              "train_seconds": rung.seconds}
    tracker.log_metrics({f"{rung.preset}/{key}": float(value) for key, value in values.items()
                         if value is not None}, step=position)


# ------------------------------------------------------------------------------------------------ table

def _cell(value: float | None, fmt: str) -> str:
    return "-" if value is None or not math.isfinite(value) else fmt.format(value)


def _compact(value: float) -> str:
    for limit, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(value) >= limit:
            return f"{value / limit:.3g}{suffix}"
    return f"{value:.3g}"


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
    lines = [caption, "", "| preset | FLOPs/px | params | ms/frame | PSNR dB | SSIM | FLIP | status | meets |",
             "|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for rung in result.rungs:
        name = f"**{rung.preset}** (chosen)" if rung.chosen else rung.preset
        meets = "-" if rung.meets is None else ("yes" if rung.meets else "no")
        status = rung.status if rung.measured else f"skipped: {rung.note}" if rung.note else "skipped"
        lines.append(f"| {name} | {_compact(rung.flops_per_pixel)} | {_compact(rung.params)} | "
                     f"{_cell(rung.ms_per_frame, '{:.3g}')} | {_cell(rung.psnr, '{:.2f}')} | "
                     f"{_cell(rung.ssim, '{:.4f}')} | {_cell(rung.flip, '{:.4f}')} | {status} | {meets} |")
    lines += ["", f"choice: {result.reason}"]
    registered = info.get("registered")
    if registered:
        lines.append(f"registered: {registered['uri']} (alias {info.get('alias')!r} -> version {registered['version']})")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ measurements

def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_method(method, width: int, height: int, *, frames: int = TIMING_FRAMES, warmup: int = TIMING_WARMUP,
                device: torch.device | str = "cpu") -> float:
    """Median ms of ``method.step`` (inference form, history carried) on synthetic WxH render frames."""
    from model.methods.registry import example_batch

    device = torch.device(device)
    method = method.for_inference().to(device)
    inputs = [example_batch(height, width, seed=seed, device=device) for seed in range(min(frames + warmup, 3))]
    seconds: list[float] = []
    state = None
    with torch.inference_mode():
        for index in range(warmup + frames):
            frame = inputs[index % len(inputs)]
            _synchronize(device)
            start = time.perf_counter()
            _, state = method.step(frame, state)
            _synchronize(device)
            if index >= warmup:
                seconds.append(time.perf_counter() - start)
    return 1000.0 * statistics.median(seconds)


def dataset_fingerprint(root: str | Path, splits: tuple[str, ...]) -> str:
    """A hash of the manifests of the dataset and of its sequences in ``splits`` (names, frames, cuts, sizes)."""
    from model.dataset import MANIFEST, Dataset

    dataset = Dataset(root)
    digest = hashlib.sha256()
    for split in splits:
        for sequence in dataset.sequences(split):
            digest.update(f"{split}/{sequence.name}\n".encode())
            digest.update((Path(sequence.path) / MANIFEST).read_bytes())
    return digest.hexdigest()


def training_key(train_config: dict[str, Any], family: str, fingerprint: str) -> str:
    """The fit key: the settings that shape the trained weights (not the preset) and the data's fingerprint."""
    values = {key: value for key, value in train_config.items() if key not in KEY_EXCLUDED}
    values.update(family=family, data=fingerprint)
    return hashlib.sha256(json.dumps(values, sort_keys=True, default=str).encode()).hexdigest()[:16]


# --------------------------------------------------------------------------------------- the whole fit

class ModelStore(Protocol):
    """The model registry as the fit needs it (``workers.tasks.fit.MLflowFit`` implements it). A version is a
    dict with at least ``name``, ``version`` and ``uri``."""

    def find_version(self, tags: dict[str, str]) -> dict[str, Any] | None:
        """The newest version whose tags include all of ``tags``."""

    def version_of_run(self, run_id: str) -> dict[str, Any] | None:
        """The newest version registered from MLflow run ``run_id``."""

    def download(self, version: dict[str, Any], folder: Path) -> Path:
        """The version's checkpoint, fetched into ``folder``."""

    def register(self, checkpoint: Path, name: str, tags: dict[str, str]) -> dict[str, Any]: ...

    def tag_version(self, version: dict[str, Any], tags: dict[str, str]) -> None: ...

    def set_alias(self, name: str, alias: str, version: str) -> None: ...


@dataclass
class FitConfig:
    family: str  # a learned registry method, without a preset
    data: str  # dataset folder
    target: str  # see Target.parse
    presets: list[str] | None = None  # None: the family's presets without a variant suffix ("xs", not "xs-int8")
    scale: int = 1
    steps: int = 1000  # training steps per preset
    crop_size: int = 64
    frames_per_sample: int = 4
    batch_size: int = 4
    lr: float = 1e-3
    warmup_steps: int = 50
    seed: int = 0
    train_split: str = "train"
    validation_split: str = "validation"
    validation_frames: int | None = None  # frames per validation sequence measured (None: all)
    time_at: tuple[int, int] = DEFAULT_TIMING_RESOLUTION  # (width, height) when the target is not ms
    timing_frames: int = TIMING_FRAMES
    timing_warmup: int = TIMING_WARMUP
    threads: int | None = None  # torch threads for training, measuring and timing (None: torch's own)
    device: str = "auto"
    out: str = "runs/fit"
    register_as: str | None = None  # None: FAMILY-fit-xSCALE
    alias: str = DEFAULT_ALIAS
    checkpoint_every: int = 500
    tracking_uri: str | None = None
    experiment: str = "denoiser"

    @property
    def registered_name(self) -> str:
        return self.register_as or f"{self.family}-fit-x{self.scale}"

    def train_config(self, preset: str, out: Path | str, register: bool):
        from model.train import TrainConfig

        return TrainConfig(
            method=f"{self.family}:{preset}", data=self.data, scale=self.scale, train_split=self.train_split,
            validation_split=self.validation_split, crop_size=self.crop_size,
            frames_per_sample=self.frames_per_sample, batch_size=self.batch_size, steps=self.steps, lr=self.lr,
            warmup_steps=self.warmup_steps, seed=self.seed, out=str(out), resume=True, device=self.device,
            checkpoint_every=self.checkpoint_every, validate_every=0, validation_frames=self.validation_frames,
            num_threads=self.threads, tracking_uri=self.tracking_uri, experiment=self.experiment,
            register_as=self.registered_name if register else None)


def default_presets(family: str) -> list[str]:
    from model.methods.registry import method_spec

    return [preset for preset in method_spec(family).presets if "-" not in preset]


@dataclass
class FitPlan:
    """Everything checked before any training: the ladder's candidates, the target, the key, the data."""

    config: FitConfig
    target: Target
    candidates: list[Candidate]
    key: str
    device: torch.device


def plan_fit(config: FitConfig) -> FitPlan:
    """Check the fit (family, presets, target, data, training settings) and cost its presets, or raise
    ValueError / KeyError naming the problem. Reads manifests and one frame per training sequence."""
    from model.dataset import Dataset
    from model.methods.registry import build_method, inference_cost, method_spec, parse_method_name
    from model.train import prepare, resolve_device

    name, preset = parse_method_name(config.family)
    if preset is not None:
        raise ValueError(f"--method takes a family (e.g. {name}), not a preset: {config.family!r}; choose presets "
                         f"with --presets")
    spec = method_spec(name)
    if not spec.learned:
        raise ValueError(f"method {name!r} has no trainable parameters; only learned families have a ladder")
    if config.scale not in spec.scales:
        raise ValueError(f"method {name!r} does not run at scale {config.scale}; scales: "
                         f"{', '.join(str(s) for s in spec.scales)}")
    presets = list(dict.fromkeys(config.presets)) if config.presets else default_presets(name)
    unknown = [p for p in presets if p not in spec.presets]
    if unknown:
        raise KeyError(f"method {name!r} has no preset {unknown[0]!r}; presets: {', '.join(spec.presets)}")
    if not presets:
        raise ValueError(f"method {name!r}: no presets to fit")
    target = Target.parse(config.target, tuple(config.time_at))
    for field_name in ("steps", "timing_frames"):
        if getattr(config, field_name) < 1:
            raise ValueError(f"{field_name} must be at least 1, got {getattr(config, field_name)}")
    if config.timing_warmup < 0:
        raise ValueError(f"timing_warmup must be >= 0, got {config.timing_warmup}")
    if not ALIAS_PATTERN.match(config.alias) or config.alias == "latest" or re.fullmatch(r"v\d+", config.alias):
        raise ValueError(f"alias {config.alias!r} is not usable: letters, digits, _ and -, not 'latest' or 'vN'")
    device = resolve_device(config.device)
    if not Dataset(config.data).names(config.validation_split):
        raise ValueError(f"dataset {config.data} has no sequences in the validation split "
                         f"{config.validation_split!r}: the fit measures every preset there")
    # The training settings and data, checked as training would (first preset; the others share them).
    prepare(config.train_config(presets[0], Path(config.out) / "_check", register=False))
    candidates = []
    for preset in presets:
        params_count, flops = inference_cost(build_method(f"{name}:{preset}", config.scale))
        candidates.append(Candidate(preset, flops, params_count))
    fingerprint = dataset_fingerprint(config.data, (config.train_split, config.validation_split))
    key = training_key(config.train_config(presets[0], "", register=False).to_dict(), name, fingerprint)
    return FitPlan(config=config, target=target, candidates=candidates, key=key, device=device)


class _Fit:
    """The real time / obtain / measure callables of one fit (run_ladder drives them)."""

    def __init__(self, plan: FitPlan, store: ModelStore | None, train_tracker: Callable[[str], Any] | None) -> None:
        self.plan = plan
        self.config = plan.config
        self.store = store
        self.train_tracker = train_tracker
        self._sequences = None

    def folder(self, preset: str) -> Path:
        return Path(self.config.out) / f"{preset}-{self.plan.key}"

    def identity_tags(self, preset: str) -> dict[str, str]:
        return {"method": self.config.family, "preset": preset, "scale": str(self.config.scale),
                "fit_key": self.plan.key}

    # -- timing
    def time_preset(self, preset: str) -> float:
        from model.methods.registry import build_method

        width, height = self.plan.target.resolution or tuple(self.config.time_at)
        with torch_threads(self.config.threads):
            method = build_method(f"{self.config.family}:{preset}", self.config.scale)
            return time_method(method, width, height, frames=self.config.timing_frames,
                               warmup=self.config.timing_warmup, device=self.plan.device)

    # -- obtaining
    def obtain(self, preset: str, progress: Progress) -> Obtained:
        started = time.perf_counter()
        reused = self._from_checkpoint(preset)
        if reused is None and self.store is not None:
            reused = self._from_registry(preset)
        if reused is not None:
            reused.seconds = time.perf_counter() - started
            return reused
        return self._train(preset, progress, started)

    def _from_checkpoint(self, preset: str) -> Obtained | None:
        from model.checkpoint import load_checkpoint
        from model.train import LAST_CHECKPOINT

        last = self.folder(preset) / LAST_CHECKPOINT
        if not last.is_file():
            return None
        checkpoint = load_checkpoint(last)
        expected = {"method": self.config.family, "preset": preset, "scale": self.config.scale}
        if checkpoint["method"] != expected:
            raise ValueError(f"{last} holds {checkpoint['method']}, not {expected}; remove it or use another --out")
        if checkpoint["step"] < self.config.steps:
            return None  # training resumes it
        registered = None
        if self.store is not None:
            # Its training run's version, else one registered by an earlier fit with this key (the same weights:
            # the same settings on the same data), else it is registered now.
            run_id = checkpoint["extra"].get("tracking_run_id")
            registered = self.store.version_of_run(run_id) if run_id else None
            registered = registered or self.store.find_version(self.identity_tags(preset))
            if registered is None:
                registered = self.store.register(last, self.config.registered_name, self._train_tags(preset, last))
            self.store.tag_version(registered, self.identity_tags(preset))
        return Obtained(last, REUSED_CHECKPOINT, registered, detail=f"checkpoint {last} (step {checkpoint['step']})")

    def _from_registry(self, preset: str) -> Obtained | None:
        version = self.store.find_version(self.identity_tags(preset))
        if version is None:
            return None
        path = self.store.download(version, self.folder(preset) / "registered")
        return Obtained(path, REUSED_REGISTRY, version, detail=f"registered {version['uri']}")

    def _train(self, preset: str, progress: Progress, started: float) -> Obtained:
        from model.train import LAST_CHECKPOINT, train

        folder = self.folder(preset)
        resuming = (folder / LAST_CHECKPOINT).is_file()
        config = self.config.train_config(preset, folder, register=self.store is not None)
        tracker = self.train_tracker(preset) if self.train_tracker is not None else None
        result = train(config, tracker=tracker, progress=progress)
        registered = result.get("registered_model")
        if registered is not None and self.store is not None:
            self.store.tag_version(registered, {**self.identity_tags(preset), "fit_dataset": str(self.config.data)})
        return Obtained(result["checkpoint"], RESUMED if resuming else TRAINED, registered,
                        seconds=time.perf_counter() - started,
                        detail=f"{result['steps']} steps" + (", resumed" if resuming else ""))

    def _train_tags(self, preset: str, checkpoint: Path) -> dict[str, str]:
        from model.checkpoint import load_checkpoint, load_method
        from model.methods.registry import inference_cost

        method = load_method(checkpoint)
        params_count, flops = inference_cost(method)
        return {"method": method.name, "preset": method.preset, "scale": str(method.scale),
                "params": str(params_count), "flops_per_pixel": f"{flops:.6g}",
                "steps": str(load_checkpoint(checkpoint)["step"]), "fit_key": self.plan.key}

    # -- measuring
    def sequences(self):
        if self._sequences is None:
            from model.evaluate import EvaluationSequence, load_split

            folders = load_split(self.config.data, self.config.validation_split, self.config.scale)
            self._sequences = [EvaluationSequence.from_sequence(s, self.config.scale, self.config.validation_frames)
                               for s in folders]
        return self._sequences

    def measure(self, preset: str, obtained: Obtained) -> Measurement:
        from model.checkpoint import load_method
        from model.evaluate import evaluate_method

        with torch_threads(self.config.threads):
            method = load_method(obtained.checkpoint, scale=self.config.scale)
            report = evaluate_method(method, self.sequences(), self.config.scale, vdp=False, device=self.plan.device)
        metrics = report["metrics"]
        return Measurement(psnr=metrics["psnr"], flip=metrics["flip"], ssim=metrics["ssim"],
                           extra={"smape": metrics["smape"], "temporal_error": metrics["temporal_error"]})


def measurement_tags(rung: Rung, timing: dict[str, Any]) -> dict[str, str]:
    """Version tags of a measured rung: validation quality and the timing with its set-up."""
    tags = {"ms_per_frame": f"{rung.ms_per_frame:.6g}", "ms_per_frame_resolution": timing["resolution"],
            "ms_per_frame_threads": str(timing["threads"]), "ms_per_frame_device": timing["device"]}
    if rung.psnr is not None:
        tags["validation_psnr"] = f"{rung.psnr:.4f}"
    if rung.ssim is not None:
        tags["validation_ssim"] = f"{rung.ssim:.4f}"
    if rung.flip is not None:
        tags["metric.validation_flip"] = f"{rung.flip:.6g}"
    return tags


def fit(config: FitConfig, *, store: ModelStore | None = None, tracker: LadderTracker | None = None,
        train_tracker: Callable[[str], Any] | None = None, progress: Progress | None = None,
        say: Say | None = None, plan: FitPlan | None = None) -> LadderResult:
    """Run the whole fit: plan (checks), ladder (time, obtain, measure, choose), then with a ``store``: tag every
    measured version with its measurements, register the choice under ``config.registered_name`` when it is not
    a version of it already, and point ``config.alias`` at it. Writes ``ladder.json`` and ``ladder.md`` to
    ``config.out`` and, with a ``tracker``, to the run. ``train_tracker(preset)`` gives each training its tracker.
    """
    plan = plan or plan_fit(config)
    worker = _Fit(plan, store, train_tracker)
    width, height = plan.target.resolution or tuple(config.time_at)
    threads = config.threads or torch.get_num_threads()
    timing = {"resolution": f"{width}x{height}",
              "output_resolution": f"{width * config.scale}x{height * config.scale}", "threads": threads,
              "device": str(plan.device), "frames": config.timing_frames, "warmup_frames": config.timing_warmup}
    if tracker is not None:
        tracker.log_params({"family": config.family, "target": str(plan.target), "scale": config.scale,
                            "presets": ",".join(c.preset for c in order_ladder(plan.candidates)),
                            "steps_per_preset": config.steps, "dataset": config.data, "fit_key": plan.key,
                            "timing_resolution": timing["resolution"], "timing_threads": threads,
                            "device": str(plan.device), "registered_name": config.registered_name,
                            "alias": config.alias})
    result = run_ladder(plan.candidates, plan.target, family=config.family, scale=config.scale,
                        time_preset=worker.time_preset, obtain=worker.obtain, measure=worker.measure,
                        tracker=tracker, progress=progress, say=say, resolution=(width, height))
    frames = "all frames" if config.validation_frames is None else f"the first {config.validation_frames} frames"
    result.info.update(dataset=config.data, fit_key=plan.key, timing=timing, out=str(config.out),
                       validation=f"the {config.validation_split!r} split ({frames} of each sequence)",
                       run_id=getattr(tracker, "run_id", None), registered=None, alias=None)
    if store is not None:
        for rung in result.rungs:
            if rung.measured and rung.registered is not None:
                store.tag_version(rung.registered, measurement_tags(rung, timing))
        chosen = result.chosen
        if chosen is not None:
            registered = chosen.registered
            if registered is None or registered.get("name") != config.registered_name:
                registered = store.register(Path(chosen.checkpoint), config.registered_name,
                                            {**worker._train_tags(chosen.preset, Path(chosen.checkpoint)),
                                             **measurement_tags(chosen, timing)})
            store.set_alias(config.registered_name, config.alias, str(registered["version"]))
            result.info.update(registered=registered, alias=config.alias)
    write_ladder(result, Path(config.out))
    if tracker is not None:
        tracker.log_params({"chosen_preset": result.chosen.preset if result.chosen else "none"})
        if result.chosen is not None:
            tracker.log_metrics({f"chosen/{key}": float(value) for key, value in (
                ("psnr", result.chosen.psnr), ("flip", result.chosen.flip),
                ("ms_per_frame", result.chosen.ms_per_frame), ("flops_per_pixel", result.chosen.flops_per_pixel))
                if value is not None}, step=0)
        tracker.log_text(LADDER_JSON, json.dumps(result.to_dict(), indent=2))
        tracker.log_text(LADDER_MARKDOWN, format_ladder(result) + "\n")
    return result


def write_ladder(result: LadderResult, folder: Path) -> dict[str, Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = {LADDER_JSON: folder / LADDER_JSON, LADDER_MARKDOWN: folder / LADDER_MARKDOWN}
    paths[LADDER_JSON].write_text(json.dumps(result.to_dict(), indent=2) + "\n")
    paths[LADDER_MARKDOWN].write_text(format_ladder(result) + "\n")
    return paths
