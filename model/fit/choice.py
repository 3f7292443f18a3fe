"""The ladder's choice, pure: order the presets, and from their measured times and quality pick the one that
meets the target. No I/O: timing, obtaining (training or reuse) and measuring come in as callables, tracking as a
small protocol, so the rules are tested with fake measurements. The rules: docs/fit.md."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

from model.fit.target import Target

Progress = Callable[[int, int, str], None]  # (current, total, message), as model.training.train's
Say = Callable[[str], None]

# Rung statuses
TRAINED, RESUMED, REUSED_CHECKPOINT, REUSED_REGISTRY, SKIPPED = (
    "trained", "resumed", "reused-checkpoint", "reused-registry", "skipped")


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
    """Time every preset, obtain and measure the ones the target needs, and choose (docs/fit.md).

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
