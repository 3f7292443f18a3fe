"""The stability suite: every method on named hard scenarios and corrupted inputs, and where each fails worst.

Scenarios (scene recipes from a dataset, and corruptions derived in memory from one clean base), the runs (as in
evaluation, a method's failure recorded rather than raised), the scores (gain over the noisy input, drop from the
method's median gain, the worst scenario) and who ghosts least. Its report and charts: ``model.evaluation.stability_report``.
Definitions and reasoning: docs/stability.md.
"""

from __future__ import annotations

import math
import os
import statistics
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from model.io.dataset import Dataset, Sequence
from model.evaluation.evaluate import EvaluationSequence, _prepare, run_sequence
from model.evaluation.ghosting import CHANGE_THRESHOLD, GHOSTING_DEFINITION, TRAIL_FRAMES, ghosting_error, trail_masks
from model.methods.base import FrameBatch, Method
from model.evaluation.metrics import VDP_DISPLAY, FovVideoVdp
from model.evaluation.tables import source_label
from model.evaluation.timing import torch_threads

__all__ = [
    "SCENE_SCENARIOS", "DERIVED_SCENARIOS", "SCENARIOS", "BASE_SCENES", "Scenario", "scale_exposure",
    "inject_non_finite", "zero_motion", "garbage_motion", "drop_optional_buffers", "derive_scenarios",
    "ScenarioPlan", "plan_scenarios", "build_scenarios", "generate_scenarios", "run_suite", "fails_worst",
    "least_ghosting",
]

SCENE_SCENARIOS: dict[str, str] = {
    "moving_object": "disocclusion: a box slides across a textured wall under a static camera",
    "moving_light": "a small light circles the objects: shadows move, history is wrong everywhere",
    "camera_cut": "a hard camera cut half-way: history must be dropped",
    "fast_camera": "a camera sweep of 4-7 degrees per frame: motion of tens of pixels",
    "metals": "smooth (mirror-like), glossy and rough metal",
    "glass": "smooth and frosted glass",
    "dark_fireflies": "a dark room lit by one tiny, very bright light: fireflies",
    "visible_emitter": "a bright, directly visible lamp crosses a finely textured wall under a static camera: "
                       "history leaves a bright trail",
    "orbiting_light": "a small bright light orbits at 20-50 degrees a frame over a slow camera orbit: shading and "
                      "shadows jump every frame",
    "sliding_over_texture": "a sphere and a textured cube slide fast over fine checker, stripes or bricks under a "
                            "static camera: ghost copies over texture",
}
EXPOSURE_BRIGHT = 16.0
EXPOSURE_DARK = 1.0 / 16.0
FIRST_FRAMES = 3
NON_FINITE_FRACTION = 0.01  # of the pixels of each corrupted buffer, per frame
DERIVED_SCENARIOS: dict[str, str] = {
    "clean": "the clean base sequence the scenarios below are made from",
    "first_frames": f"frames 0-{FIRST_FRAMES - 1} of the base: before any history exists",
    "exposure_bright": f"radiance and references x{EXPOSURE_BRIGHT:g} (albedo, normals, depth unchanged)",
    "exposure_dark": f"radiance and references x1/{1 / EXPOSURE_DARK:g} (albedo, normals, depth unchanged)",
    "nan_inf_color": f"NaN, +Inf and -Inf in {NON_FINITE_FRACTION:.0%} of the pixels of color, diffuse and specular "
                     "(other pixels in each)",
    "nan_inf_guides": f"NaN / Inf in {NON_FINITE_FRACTION:.0%} of the pixels of albedo, normal, depth, motion, "
                      "roughness, specular albedo; NaN jitter on odd frames",
    "zero_motion": "motion vectors all 0",
    "garbage_motion": "motion vectors uniformly random, up to half the image size",
    "missing_buffers": "diffuse, specular, specular_albedo and roughness removed",
}
SCENARIOS: tuple[str, ...] = tuple(SCENE_SCENARIOS) + tuple(DERIVED_SCENARIOS)
BASE_SCENES = ("diffuse_room", "textured_detail", "swinging_light")  # preferred clean bases, in order
SPLIT_PREFERENCE = ("test", "validation", "train")
MIN_DROP_DB = 0.05  # a largest drop below this names no worst scenario (the method is as good everywhere)
DEFINITION = (
    "gain = the method's PSNR minus the noisy input's PSNR on the same frames (the 1spp color, sanitized, "
    "bicubic-upscaled when the output is at scale 2), which removes how hard the scene is; drop = the method's "
    "median gain over the scenarios it completed minus its gain in the scenario. A method fails worst in the "
    "scenario with the largest drop (none when every drop is under {min:g} dB); a scenario where it raised an error "
    "or returned a non-finite output is a failure and comes before any drop.").format(min=MIN_DROP_DB)
FRAME_METRICS = ("psnr", "ssim", "flip", "smape")
SEQUENCE_METRICS = ("temporal_error", "fvvdp_jod")
INPUT_LABEL = "input (1spp)"

Progress = Callable[[str], None]


@dataclass
class Scenario:
    """One scenario: its frames in memory (references at the suite's scale), where they come from."""

    name: str
    description: str
    sequence: EvaluationSequence
    source: str  # the dataset sequence the frames come from
    derived: bool = False  # made from the clean base (comparable with the 'clean' scenario)
    # The motion the trail region is measured with: the frames' own unless a derived scenario corrupted them
    # (zero_motion, garbage_motion, nan_inf_guides), where the clean base's motion still says what moved.
    true_motion: list[torch.Tensor] | None = None

    @property
    def frames(self) -> list[FrameBatch]:
        return self.sequence.frames

    def references(self) -> torch.Tensor:
        """The references of every frame, (T, 3, H, W) at the suite's scale."""
        return torch.cat([frame.reference for frame in self.frames])

    def trails(self) -> torch.Tensor:
        """The trail region of every frame (``model.evaluation.ghosting.trail_masks``), (T, 1, H, W) bool."""
        motion = torch.cat(self.true_motion if self.true_motion is not None else [f.motion for f in self.frames])
        return trail_masks(self.references(), motion, self.sequence.camera_cuts)


# -------------------------------------------------------------------------------------------- transforms

RADIANCE = ("color", "diffuse", "specular")


def scale_exposure(frames: list[FrameBatch], factor: float) -> list[FrameBatch]:
    """Radiance (color, diffuse, specular) and the reference times ``factor``; every other buffer unchanged."""
    return [replace(f, **{name: getattr(f, name) * factor for name in RADIANCE + ("reference",)
                          if getattr(f, name) is not None}) for f in frames]


def inject_non_finite(frames: list[FrameBatch], buffers: tuple[str, ...], fraction: float = NON_FINITE_FRACTION,
                      seed: int = 0) -> list[FrameBatch]:
    """In each buffer present, ``fraction`` of the pixels (at least 3; all channels; seeded positions, new ones
    per frame and buffer) set to NaN, +Inf and -Inf, a third each. Missing buffers are skipped; the references
    are never touched."""
    corrupted = []
    for index, frame in enumerate(frames):
        generator = torch.Generator().manual_seed(seed * 100_003 + index)
        changes = {}
        for name in buffers:
            tensor = getattr(frame, name)
            if tensor is None:
                continue
            pixels = tensor.shape[2] * tensor.shape[3]
            count = min(pixels, max(3, round(fraction * pixels)))
            chosen = torch.randperm(pixels, generator=generator)[:count]
            values = torch.full((count,), -math.inf)
            values[: count // 3] = math.nan
            values[count // 3: 2 * count // 3] = math.inf
            flat = tensor.clone().flatten(2)  # (N, C, H*W)
            flat[:, :, chosen.to(tensor.device)] = values.to(tensor)
            changes[name] = flat.view_as(tensor)
        corrupted.append(replace(frame, **changes))
    return corrupted


def zero_motion(frames: list[FrameBatch]) -> list[FrameBatch]:
    return [replace(f, motion=torch.zeros_like(f.motion)) for f in frames]


def garbage_motion(frames: list[FrameBatch], seed: int = 0) -> list[FrameBatch]:
    """Motion vectors drawn uniformly in [-W/2, W/2] x [-H/2, H/2] pixels, seeded per frame."""
    result = []
    for index, frame in enumerate(frames):
        generator = torch.Generator().manual_seed(seed * 100_003 + index)
        noise = torch.rand(frame.motion.shape, generator=generator) * 2 - 1
        half = torch.tensor([frame.width / 2, frame.height / 2]).view(1, 2, 1, 1)
        result.append(replace(frame, motion=(noise * half).to(frame.motion)))
    return result


def drop_optional_buffers(frames: list[FrameBatch]) -> list[FrameBatch]:
    return [replace(f, diffuse=None, specular=None, specular_albedo=None, roughness=None) for f in frames]


def _nan_jitter_on_odd_frames(frames: list[FrameBatch]) -> list[FrameBatch]:
    return [replace(f, jitter=torch.full_like(f.jitter, math.nan)) if i % 2 else f for i, f in enumerate(frames)]


def derive_scenarios(clean: EvaluationSequence, names: tuple[str, ...] = tuple(DERIVED_SCENARIOS),
                     seed: int = 0) -> list[Scenario]:
    """The derived scenarios among ``names``, made from the clean sequence ``clean`` (never modified)."""
    unknown = [n for n in names if n not in DERIVED_SCENARIOS]
    if unknown:
        raise ValueError(f"unknown derived scenario {', '.join(map(repr, unknown))}; derived scenarios: "
                         f"{', '.join(DERIVED_SCENARIOS)}")
    frames, cuts = clean.frames, clean.camera_cuts
    guides = ("albedo", "normal", "depth", "motion", "roughness", "specular_albedo")
    makers: dict[str, Callable[[], tuple[list[FrameBatch], list[bool]]]] = {
        "clean": lambda: (list(frames), list(cuts)),
        "first_frames": lambda: (frames[:FIRST_FRAMES], cuts[:FIRST_FRAMES]),
        "exposure_bright": lambda: (scale_exposure(frames, EXPOSURE_BRIGHT), list(cuts)),
        "exposure_dark": lambda: (scale_exposure(frames, EXPOSURE_DARK), list(cuts)),
        "nan_inf_color": lambda: (inject_non_finite(frames, RADIANCE, seed=seed), list(cuts)),
        "nan_inf_guides": lambda: (_nan_jitter_on_odd_frames(inject_non_finite(frames, guides, seed=seed + 1)),
                                   list(cuts)),
        "zero_motion": lambda: (zero_motion(frames), list(cuts)),
        "garbage_motion": lambda: (garbage_motion(frames, seed=seed), list(cuts)),
        "missing_buffers": lambda: (drop_optional_buffers(frames), list(cuts)),
    }
    scenarios = []
    optional = ("diffuse", "specular", "specular_albedo", "roughness")
    for name in DERIVED_SCENARIOS:
        if name in names:
            made, made_cuts = makers[name]()
            description = DERIVED_SCENARIOS[name]
            if name == "missing_buffers" and all(getattr(f, b) is None for f in frames for b in optional):
                description += " (the base sequence has none of them: the same frames as 'clean')"
            scenarios.append(Scenario(name, description,
                                      EvaluationSequence(name, made, made_cuts, clean.scale), clean.name,
                                      derived=True, true_motion=[f.motion for f in frames[:len(made)]]))
    return scenarios


# ------------------------------------------------------------------------------------------ from a dataset

def _ordered_sequences(dataset: Dataset) -> list[Sequence]:
    """Every sequence, test split first, then validation, then train (dataset order within a split)."""
    return [sequence for split in SPLIT_PREFERENCE for sequence in dataset.sequences(split)]


def _pick_base(sequences: list[Sequence], base: str | None) -> Sequence:
    if base is not None:
        for sequence in sequences:
            if sequence.name == base:
                return sequence
        raise ValueError(f"no sequence {base!r} in the dataset; it has: "
                         f"{', '.join(s.name for s in sequences) or 'none'}")
    for scene in BASE_SCENES:
        for sequence in sequences:
            if sequence.scene == scene:
                return sequence
    others = [s for s in sequences if s.scene not in SCENE_SCENARIOS]
    return (others or sequences)[0]


@dataclass
class ScenarioPlan:
    """Where each scenario's frames come from, read from the manifests alone (no frame decoded)."""

    scenes: dict[str, Sequence]  # scene scenario -> the sequence of that scene it runs on
    base: Sequence | None  # the clean sequence of the derived scenarios (None when none is asked for)
    derived: tuple[str, ...]
    missing: list[dict]  # {"name", "reason"} of the scene scenarios the dataset has no usable sequence for

    @property
    def names(self) -> list[str]:
        return list(self.scenes) + list(self.derived)


def plan_scenarios(dataset_dir: str | os.PathLike, scale: int = 1, *, names: tuple[str, ...] = SCENARIOS,
                   base: str | None = None) -> ScenarioPlan:
    """The sequences the scenarios ``names`` would use; ValueError for an unknown scenario, an empty dataset, an
    unknown base or one without references at ``scale``. Derived scenarios are made from ``base`` (a sequence
    name), by default the first of BASE_SCENES present, else the first sequence that is no scene scenario."""
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenario {', '.join(map(repr, unknown))}; scenarios: {', '.join(SCENARIOS)}")
    dataset = Dataset(dataset_dir)
    sequences = _ordered_sequences(dataset)
    if not sequences:
        raise ValueError(f"dataset {dataset.root} has no sequences")
    scenes: dict[str, Sequence] = {}
    missing: list[dict] = []
    for name in SCENE_SCENARIOS:
        if name not in names:
            continue
        matches = [s for s in sequences if s.scene == name]
        usable = [s for s in matches if scale in s.scales]
        if not usable:
            reason = (f"no sequence of scene '{name}' in the dataset" if not matches else
                      f"sequence '{matches[0].name}' has no references at scale {scale}")
            missing.append({"name": name, "reason": reason})
            continue
        scenes[name] = usable[0]
    derived = tuple(n for n in names if n in DERIVED_SCENARIOS)
    chosen = _pick_base(sequences, base) if derived else None
    if chosen is not None and scale not in chosen.scales:
        present = ", ".join(str(s) for s in chosen.scales) or "none"
        raise ValueError(f"sequence '{chosen.name}' ({chosen.path}) has no references at scale {scale} "
                         f"(scales present: {present})")
    return ScenarioPlan(scenes, chosen, derived, missing)


def build_scenarios(dataset_dir: str | os.PathLike, scale: int = 1, *, names: tuple[str, ...] = SCENARIOS,
                    base: str | None = None, frame_limit: int | None = None,
                    seed: int = 0) -> tuple[list[Scenario], list[dict]]:
    """The scenarios ``names`` from a dataset (as ``plan_scenarios`` finds them): (scenarios, missing), missing =
    [{"name", "reason"}] for scene scenarios the dataset has no usable sequence for."""
    if frame_limit is not None and frame_limit < 1:
        raise ValueError(f"frame limit must be positive, got {frame_limit}")
    plan = plan_scenarios(dataset_dir, scale, names=names, base=base)
    scenarios: list[Scenario] = []
    for name, source in plan.scenes.items():
        sequence = EvaluationSequence.from_sequence(source, scale, frame_limit)
        scenarios.append(Scenario(name, SCENE_SCENARIOS[name], replace(sequence, name=name), source.name))
    if plan.base is not None:
        clean = EvaluationSequence.from_sequence(plan.base, scale, frame_limit)
        scenarios += derive_scenarios(clean, plan.derived, seed=seed)
    return scenarios, plan.missing


def generate_scenarios(root: str | os.PathLike, *, size: tuple[int, int] = (64, 64), frames: int = 8,
                       ref_spp: int = 64, scale: int = 1, seed: int = 0, names: tuple[str, ...] = SCENARIOS,
                       variant: str | None = None, progress: Progress | None = None) -> Path:
    """Render the scene scenarios among ``names`` (and ``diffuse_room``, the clean base, when a derived scenario
    is asked for) with the Mitsuba generator into the dataset ``root`` (test split); returns ``root``.

    A sequence already there with the same size, frame count and the needed reference scale is reused.
    """
    from model.data.generate import default_sequence_name, generate_sequence
    from model.data.render import RenderSettings

    scenes = [n for n in SCENE_SCENARIOS if n in names]
    if any(n in DERIVED_SCENARIOS for n in names):
        scenes.append(BASE_SCENES[0])
    settings = RenderSettings(width=size[0], height=size[1], ref_spp=ref_spp,
                              ref_scales=(1,) if scale == 1 else (1, scale), variant=variant)
    root = Path(root)
    say = progress or (lambda message: None)
    existing = Dataset(root) if (root / "manifest.json").exists() else None
    for scene in scenes:
        name = default_sequence_name(scene, seed)
        if existing is not None and name in existing.names():
            sequence = existing.sequence(name)
            same_size = (sequence.width, sequence.height) == tuple(size)
            if same_size and len(sequence) == frames and scale in sequence.scales:
                say(f"reusing {root / name}")
                continue
        say(f"rendering {scene}: {frames} frames at {size[0]}x{size[1]}, references {ref_spp} spp")
        generate_sequence(scene, root, frames=frames, settings=settings, seed=seed, split="test", name=name,
                          overwrite=True, progress=False,
                          on_frame=lambda done, total, message: say(message))
    return root


# ----------------------------------------------------------------------------------------------- running

def _run(method: Method, scenario: Scenario, metric: FovVideoVdp | None, device: torch.device,
         trails: torch.Tensor) -> dict:
    """One method on one scenario; any exception is the method failing there (recorded, not raised).
    ``trails``: the scenario's trail region, where its ghosting is measured."""
    try:
        run = run_sequence(method, scenario.sequence, vdp=metric, warmup_frames=0, device=device, keep_outputs=True)
    except Exception as error:  # noqa: BLE001 - the suite's job is to record how methods fail
        return {"status": "failed", "error": f"{type(error).__name__}: {error}"}
    ghosting = ghosting_error(run["outputs"], scenario.references(), trails)
    result = {"status": "ok", "error": None, **run["metrics"], "per_frame_psnr": run["per_frame"]["psnr"],
              "sanitized": run["sanitized"], "keeps_history": run["keeps_history"], "output_ratio": run["output_ratio"],
              "ghost_error": ghosting["error"] if ghosting else None,
              "ghost_psnr": ghosting["psnr"] if ghosting else None,
              "per_frame_ghost_error": ghosting["per_frame_error"] if ghosting else None}
    if "fvvdp_error" in run:
        result["fvvdp_error"] = run["fvvdp_error"]
    return result


def run_suite(scenarios: list[Scenario], methods: list[Method | str], scale: int = 1, *, vdp: bool = False,
              device: torch.device | str = "cpu", threads: int | None = None, progress: Progress | None = None,
              missing: list[dict] | None = None, data: str | None = None) -> dict:
    """Every method on every scenario; returns the JSON-serializable report (scores and worst scenarios).

    ``methods`` are ``NAME[:PRESET]`` texts, checkpoint files or Method objects; a bad one raises before any run.
    The noisy input (the ``identity`` method) always runs too: it is what the gains are measured against.
    """
    if not methods:
        raise ValueError("no methods to run")
    if not scenarios:
        raise ValueError("no scenarios to run")
    say = progress or (lambda message: None)
    device = torch.device(device)
    entrants = [_prepare(m, scale) for m in methods]
    baseline, _ = _prepare("identity", scale)
    with torch_threads(threads):
        metric = FovVideoVdp(device) if vdp else None
        usable = metric if metric is not None and metric.available else None
        trails = {scenario.name: scenario.trails() for scenario in scenarios}
        inputs = {}
        for scenario in scenarios:
            inputs[scenario.name] = _run(baseline.to(device), scenario, None, device, trails[scenario.name])
        entries = []
        for method, source in entrants:
            method.to(device)
            runs = {}
            for scenario in scenarios:
                say(f"{method.label}: {scenario.name} ({len(scenario.frames)} frames)")
                runs[scenario.name] = _run(method, scenario, usable, device, trails[scenario.name])
                if runs[scenario.name]["status"] == "failed":
                    say(f"{method.label}: {scenario.name} FAILED: {runs[scenario.name]['error']}")
            # Temporal: it carried a state from one frame to the next (per-frame methods return {}).
            temporal = any(run.get("keeps_history") for run in runs.values())
            entries.append({"label": method.label, "source": source, "temporal": temporal, "scenarios": runs})
        name_shared_labels(entries)
        threads_used = torch.get_num_threads()
    first = scenarios[0].sequence
    report = {
        "suite": "stability",
        "data": data,
        "scale": scale,
        "device": str(device),
        "threads": threads_used,
        "torch_version": torch.__version__,
        "input_resolution": first.input_resolution,
        "output_resolution": first.output_resolution,
        "definition": DEFINITION,
        "scenarios": [{"name": s.name, "description": s.description, "source": s.source, "derived": s.derived,
                       "frames": len(s.frames), "camera_cuts": [i for i, c in enumerate(s.sequence.camera_cuts) if c],
                       "sanitized": inputs[s.name].get("sanitized"), "trail": _trail_summary(trails[s.name])}
                      for s in scenarios],
        "missing_scenarios": list(missing or []),
        "fvvdp": {"enabled": metric is not None, "available": usable is not None,
                  "reason": None if metric is None else metric.unavailable_reason, "display": VDP_DISPLAY},
        "input": {name: {"label": INPUT_LABEL if scale == 1 else f"input (1spp, bicubic x{scale})",
                         "status": run["status"], "error": run["error"], "psnr": run.get("psnr"),
                         "per_frame_psnr": run.get("per_frame_psnr"), "ghost_error": run.get("ghost_error"),
                         "ghost_psnr": run.get("ghost_psnr"), "per_frame_ghost_error": run.get("per_frame_ghost_error")}
                  for name, run in inputs.items()},
        "methods": entries,
    }
    score(report)
    report["ghosting"] = least_ghosting(report)
    return report


def name_shared_labels(entries: list[dict]) -> None:
    """Entries of one method from several models (a pretrained one, a fine-tune) share a label, and the ghosting
    summary, keyed by label, would merge them: such labels get their source appended (model.evaluation.tables.source_label)."""
    labels = [entry["label"] for entry in entries]
    for entry in entries:
        entry["label"] = source_label(entry["label"], entry["source"], labels)


def _trail_summary(trails: torch.Tensor) -> dict:
    """How much of a scenario its trail region covers: frames with a trail, and the mean fraction of their
    pixels in it (None without any)."""
    coverage = [float(trail.float().mean()) for trail in trails if bool(trail.any())]
    return {"frames": len(coverage), "coverage": statistics.fmean(coverage) if coverage else None,
            "per_frame_coverage": [float(trail.float().mean()) for trail in trails]}


# ------------------------------------------------------------------------------------------------ scoring

def fails_worst(psnr: dict[str, float | None], input_psnr: dict[str, float | None],
                failures: dict[str, str] | None = None, order: list[str] | None = None) -> dict:
    """Where a method fails worst (see DEFINITION): its per-scenario PSNR (None for a failure), the input's PSNR
    on the same scenarios, and the failures' reasons. Returns {"scenario", "failed", "reason", "drop_db",
    "gain_db", "median_gain_db", "gains": {scenario: gain}, "drops": {scenario: drop}}."""
    failures = dict(failures or {})
    order = order or list(psnr)
    for name in order:
        if psnr.get(name) is None and name not in failures:
            failures[name] = "no result"
    gains = {name: psnr[name] - input_psnr[name] for name in order
             if psnr.get(name) is not None and input_psnr.get(name) is not None}
    median = statistics.median(gains.values()) if gains else None
    drops = {name: median - gain for name, gain in gains.items()} if median is not None else {}
    result = {"scenario": None, "failed": False, "reason": None, "drop_db": None, "gain_db": None,
              "median_gain_db": median, "gains": gains, "drops": drops}
    failed = [name for name in order if name in failures]
    if failed:
        name = failed[0]
        return {**result, "scenario": name, "failed": True, "reason": failures[name]}
    if drops:
        name = max(drops, key=lambda n: (drops[n], -order.index(n)))
        if drops[name] >= MIN_DROP_DB:
            return {**result, "scenario": name, "drop_db": drops[name], "gain_db": gains[name]}
    return result


def score(report: dict) -> None:
    """Fill gains, drops, differences to the clean scenario and the worst scenario into every method entry."""
    order = [s["name"] for s in report["scenarios"]]
    derived = {s["name"] for s in report["scenarios"] if s["derived"]}
    input_psnr = {name: report["input"][name]["psnr"] for name in order}
    for entry in report["methods"]:
        runs = entry["scenarios"]
        psnr = {name: runs[name].get("psnr") for name in order}
        failures = {name: runs[name]["error"] for name in order if runs[name]["status"] == "failed"}
        worst = fails_worst(psnr, input_psnr, failures, order)
        clean = psnr.get("clean")
        for name in order:
            run = runs[name]
            run["gain_db"] = worst["gains"].get(name)
            run["drop_db"] = worst["drops"].get(name)
            run["vs_clean_db"] = (run["psnr"] - clean if name in derived and name != "clean" and clean is not None
                                  and run.get("psnr") is not None else None)
        entry["median_gain_db"] = worst["median_gain_db"]
        entry["failures"] = [{"scenario": name, "error": reason} for name, reason in failures.items()]
        entry["worst"] = {key: worst[key] for key in ("scenario", "failed", "reason", "drop_db", "gain_db")}
        if worst["scenario"] is not None and not worst["failed"]:
            entry["worst"]["psnr"] = psnr[worst["scenario"]]


def least_ghosting(report: dict) -> dict:
    """Which temporal method ghosts least (``model.evaluation.ghosting``): per scenario with a trail, the temporal method with
    the lowest ghost error; overall, the one with the lowest mean ghost error over the scenarios where every
    temporal method has one (so each mean covers the same scenes). Per-frame methods cannot ghost and are left
    out. Returns {"definition", "trail_frames", "threshold", "temporal": [labels], "by_scenario": {scenario:
    label or None}, "mean_error": {label: mean}, "common_scenarios": [...], "least": label or None}."""
    temporal = [entry for entry in report["methods"] if entry.get("temporal")]
    with_trail = [s["name"] for s in report["scenarios"] if s["trail"]["frames"]]
    by_scenario = {}
    for name in with_trail:
        scored = [(entry["scenarios"][name]["ghost_error"], entry["label"]) for entry in temporal
                  if entry["scenarios"][name].get("ghost_error") is not None]
        by_scenario[name] = min(scored)[1] if scored else None
    common = [name for name in with_trail
              if all(entry["scenarios"][name].get("ghost_error") is not None for entry in temporal)]
    means = {entry["label"]: statistics.fmean(entry["scenarios"][name]["ghost_error"] for name in common)
             for entry in temporal} if common else {}
    return {"definition": GHOSTING_DEFINITION, "trail_frames": TRAIL_FRAMES, "threshold": CHANGE_THRESHOLD,
            "temporal": [entry["label"] for entry in temporal], "by_scenario": by_scenario, "mean_error": means,
            "common_scenarios": common, "least": min(means, key=means.get) if means else None}
