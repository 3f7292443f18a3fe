"""Running a fit: the real time / obtain / measure callables of a plan (a preset's speed timed before any
training; weights reused from the fit's own folder or the registry before anything is trained), driven by the
ladder's choice, then the choice registered and aliased and the ladder written. MLflow comes in through
``ModelStore`` and ``LadderTracker`` (``workers.tasks.fit``). Details: docs/fit.md."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import torch

from model.fit.choice import (
    RESUMED,
    REUSED_CHECKPOINT,
    REUSED_REGISTRY,
    TRAINED,
    LadderResult,
    LadderTracker,
    Measurement,
    Obtained,
    Progress,
    Rung,
    Say,
    order_ladder,
    run_ladder,
)
from model.fit.plan import FitConfig, FitPlan, plan_fit
from model.fit.report import LADDER_JSON, LADDER_MARKDOWN, format_ladder, write_ladder
from model.evaluation.timing import time_method, torch_threads


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
            if self.config.shipped_settings:  # timed as its training will run it
                method.use_shipped_settings()
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
        from model.training.checkpoint import load_checkpoint
        from model.training.train import LAST_CHECKPOINT

        last = self.folder(preset) / LAST_CHECKPOINT
        if not last.is_file():
            return None
        checkpoint = load_checkpoint(last)
        expected = {"method": self.config.family, "preset": preset, "scale": self.config.scale}
        if checkpoint["method"] != expected:
            raise ValueError(f"{last} holds {checkpoint['method']}, not {expected}; remove it or use another --out")
        if checkpoint["step"] < checkpoint["extra"].get("total_steps", self.config.steps):
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
        from model.training.train import LAST_CHECKPOINT, train

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
        from model.training.checkpoint import load_checkpoint, load_method
        from model.methods.registry import inference_cost

        method = load_method(checkpoint)
        params_count, flops = inference_cost(method)
        return {"method": method.name, "preset": method.preset, "scale": str(method.scale),
                "params": str(params_count), "flops_per_pixel": f"{flops:.6g}",
                "steps": str(load_checkpoint(checkpoint)["step"]), "fit_key": self.plan.key}

    # -- measuring
    def sequences(self):
        if self._sequences is None:
            from model.evaluation.evaluate import EvaluationSequence, load_split

            folders = load_split(self.config.data, self.config.validation_split, self.config.scale)
            self._sequences = [EvaluationSequence.from_sequence(s, self.config.scale, self.config.validation_frames)
                               for s in folders]
        return self._sequences

    def measure(self, preset: str, obtained: Obtained) -> Measurement:
        from model.training.checkpoint import load_method
        from model.evaluation.evaluate import evaluate_method

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
