"""Pretrained models shipped in the repository: ``pretrained/<NAME>/model.pt`` + ``pretrained/<NAME>/manifest.json``.

A shipped model is a checkpoint stripped to what inference needs (weights, method, training settings, step; no
optimizer or RNG state), named like a registered model (``fused-balanced-x1``: METHOD-PRESET-xSCALE), with a
manifest::

    {"format": "denoiser-pretrained/1", "name", "method", "preset", "scale", "params",
     "file": "model.pt", "sha256": hex digest of the file, "bytes": its size,
     "training": {"script", "dataset": {"path", "script", "digest", "splits": {split: {"sequences", "scenes"}}},
                  "steps", "step", "seed", "best_metric", "train_config", "stages": [earlier trainings]},
     "held_out": {"status": "measured" | "pending", ...}}

``held_out`` is copied from an evaluation report (``denoiser evaluate --out``) of the same run: the shipped model's
row and the OIDN rows (OIDN and OIDN + TAA at each quality), timed in that run on the same frames. Without a report
it says "pending": numbers are never made up here.

Loading checks the file's sha256 against the manifest first, so a damaged or replaced file is refused naming the
file and the fix, before torch reads a byte of it. ``ship_checkpoint`` writes a model (``scripts/ship_pretrained.py``
is its command line; the reproduction scripts call it after training and evaluation).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from model.methods.base import Method
from model.methods.fused import RUN_TIME_SETTINGS  # shipped with the weights unchanged (ship_checkpoint)
from model.methods.history_rectification import HISTORY_SETTINGS  # the seed methods', the same way

PRETRAINED_FORMAT = "denoiser-pretrained/1"
# Where a ``root`` of None looks: the checkout's folder. The library reads no settings; the entry points pass the
# configured folder (core.settings.Settings.pretrained_dir, which an installed package's deployment sets).
PRETRAINED_DIR = Path(__file__).resolve().parents[2] / "pretrained"
MANIFEST = "manifest.json"
WEIGHTS = "model.pt"
NAME = re.compile(r"^[a-z0-9][a-z0-9.-]{0,99}$")
# Rows of an evaluation report copied next to the shipped model's: the outside peer at each quality.
PEER_METHODS = ("oidn", "oidn-taa")
METRICS = ("psnr", "ssim", "flip", "smape", "temporal_error", "fvvdp_jod")


class PretrainedError(ValueError):
    """A shipped model that exists but cannot be used (damaged, missing or mismatched file; bad manifest)."""


class UnknownPretrained(KeyError):
    """No shipped model has this name (the message lists those that exist)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


@dataclass(frozen=True)
class PretrainedModel:
    name: str
    folder: Path
    manifest: dict[str, Any]

    @property
    def path(self) -> Path:
        return self.folder / self.manifest["file"]

    @property
    def method(self) -> str:
        return self.manifest["method"]

    @property
    def preset(self) -> str:
        return self.manifest["preset"]

    @property
    def scale(self) -> int:
        return int(self.manifest["scale"])

    @property
    def sha256(self) -> str:
        return self.manifest["sha256"]

    @property
    def held_out(self) -> dict[str, Any]:
        return self.manifest.get("held_out") or {"status": "pending"}

    def held_out_row(self) -> dict[str, Any] | None:
        """The shipped model's own held-out row, or None while pending."""
        return self.held_out.get("model") if self.held_out.get("status") == "measured" else None


def score_text(row: dict[str, Any] | None, key: str, fmt: str) -> str:
    """One score of a held-out row formatted, "-" when absent."""
    return "-" if not row or row.get(key) is None else format(row[key], fmt)


def peer_row(model: PretrainedModel, label: str) -> dict[str, Any] | None:
    """The held-out row of the peer ``label`` (e.g. ``oidn:high``) from the model's evaluation run, if measured."""
    return next((peer for peer in model.held_out.get("peers") or [] if peer.get("label") == label), None)


def held_out_markdown(models: list[PretrainedModel]) -> str:
    """Each model's held-out row next to the OIDN and OIDN + TAA rows of the same evaluation run, as Markdown."""
    lines = ["| model | row | PSNR dB ↑ | SSIM ↑ | FLIP ↓ | temporal ↓ | JOD ↑ | ms/frame | time / OIDN-high |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for model in models:
        held_out = model.held_out
        if held_out.get("status") != "measured":
            lines.append(f"| {model.name} | held-out evaluation pending | - | - | - | - | - | - | - |")
            continue
        for row in [held_out["model"], *(held_out.get("peers") or [])]:
            label = f"**{row['label']}** (shipped)" if row is held_out["model"] else row["label"]
            lines.append(f"| {model.name} | {label} | {score_text(row, 'psnr', '.2f')} | "
                         f"{score_text(row, 'ssim', '.4f')} | {score_text(row, 'flip', '.4f')} | "
                         f"{score_text(row, 'temporal_error', '.5f')} | {score_text(row, 'fvvdp_jod', '.2f')} | "
                         f"{score_text(row, 'ms_per_frame', '.1f')} | {score_text(row, 'time_ratio_to_oidn', '.3g')} |")
    return "\n".join(lines)


def _root(root: str | os.PathLike | None) -> Path:
    return Path(root) if root is not None else PRETRAINED_DIR


def pretrained_names(root: str | os.PathLike | None = None) -> list[str]:
    """Names of the shipped models (folders holding a manifest), sorted."""
    folder = _root(root)
    if not folder.is_dir():
        return []
    return sorted(child.name for child in folder.iterdir() if (child / MANIFEST).is_file() and NAME.match(child.name))


def is_pretrained(name: str, root: str | os.PathLike | None = None) -> bool:
    if not NAME.match(name):
        return False
    try:
        return (_root(root) / name / MANIFEST).is_file()
    except OSError:  # a name the file system refuses cannot be a shipped model
        return False


def get_pretrained(name: str, root: str | os.PathLike | None = None) -> PretrainedModel:
    """The shipped model ``name`` with its manifest read and checked (not its weights: ``verify`` does that)."""
    if not is_pretrained(name, root):
        known = ", ".join(pretrained_names(root)) or "none"
        raise UnknownPretrained(f"no pretrained model named {name!r} (pretrained models: {known})")
    folder = _root(root) / name
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError) as error:
        raise PretrainedError(f"pretrained model {name!r}: {folder / MANIFEST} is not readable JSON ({error}); "
                              f"restore it from the repository (git checkout -- {folder / MANIFEST})") from None
    missing = [key for key in ("format", "method", "preset", "scale", "file", "sha256") if key not in manifest] \
        if isinstance(manifest, dict) else ["(not an object)"]
    if missing or manifest.get("format") != PRETRAINED_FORMAT:
        raise PretrainedError(f"pretrained model {name!r}: {folder / MANIFEST} is not a {PRETRAINED_FORMAT} manifest"
                              + (f" (missing: {', '.join(missing)})" if missing else ""))
    if Path(manifest["file"]).name != manifest["file"]:
        raise PretrainedError(f"pretrained model {name!r}: manifest file {manifest['file']!r} is not a plain name")
    return PretrainedModel(name=name, folder=folder, manifest=manifest)


def file_sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def verify(model: PretrainedModel) -> Path:
    """The weights file, after checking it exists and its sha256 is the manifest's; else PretrainedError."""
    path = model.path
    if not path.is_file():
        raise PretrainedError(f"pretrained model {model.name!r}: weights file {path} is missing; restore it from the "
                              f"repository (git checkout -- {path}; with Git LFS: git lfs pull)")
    actual = file_sha256(path)
    if actual != model.sha256:
        raise PretrainedError(f"pretrained model {model.name!r}: {path} has sha256 {actual[:12]}..., the manifest "
                              f"says {model.sha256[:12]}...: the file is damaged or was replaced; restore it from the "
                              f"repository (git checkout -- {path})")
    return path


def load_pretrained(name: str, device: str | torch.device = "cpu", scale: int | None = None,
                    root: str | os.PathLike | None = None) -> Method:
    """The shipped model's method with its weights, in eval mode (sha256 checked first)."""
    from model.training.checkpoint import load_method

    model = get_pretrained(name, root)
    path = verify(model)
    try:
        return load_method(path, device, scale=scale)
    except (KeyError, RuntimeError) as error:  # a manifest and file that verify but do not fit the code
        message = error.args[0] if error.args else error
        raise PretrainedError(f"pretrained model {name!r}: {path} does not load: {message}") from None


# ------------------------------------------------------------------------------------------------ shipping

def dataset_summary(dataset_dir: str | os.PathLike) -> dict[str, Any]:
    """A dataset's recipe as its manifest records it: per split the sequences and scene recipes, and the sha256 of
    the dataset manifest plus every sequence manifest (the same digest the training run's lineage records)."""
    from model.io.dataset import Dataset, dataset_digest

    dataset = Dataset(dataset_dir)
    splits = {}
    for split in ("train", "validation", "test"):
        sequences = dataset.sequences(split)
        splits[split] = {"sequences": len(sequences),
                         "scenes": sorted({s.scene for s in sequences if s.scene is not None})}
    return {"digest": dataset_digest(dataset_dir), "splits": splits}


def held_out_from_report(report: dict[str, Any], row_source: str, method: str, preset: str,
                         scale: int) -> dict[str, Any]:
    """The ``held_out`` section from an evaluation report: the row whose ``source`` is ``row_source`` (checked to
    be ``method:preset`` at ``scale``) and every OIDN / OIDN + TAA row of the same run."""
    if int(report.get("scale", 0)) != scale:
        raise PretrainedError(f"the evaluation report is at scale {report.get('scale')}, the model at scale {scale}")
    rows = report.get("methods") or []
    own = [row for row in rows if row.get("source") == row_source]
    if len(own) != 1:
        sources = ", ".join(str(row.get("source")) for row in rows)
        raise PretrainedError(f"the evaluation report has {len(own)} rows from {row_source!r} (sources: {sources})")
    row = own[0]
    if (row.get("method"), row.get("preset")) != (method, preset):
        raise PretrainedError(f"the report's row from {row_source!r} is {row.get('method')}:{row.get('preset')}, "
                              f"not {method}:{preset}")

    def brief(entry: dict[str, Any]) -> dict[str, Any]:
        metrics = entry.get("metrics") or {}
        return {"label": entry.get("label"), **{key: metrics.get(key) for key in METRICS},
                "ms_per_frame": entry.get("ms_per_frame"), "time_ratio_to_oidn": entry.get("time_ratio_to_oidn")}

    return {"status": "measured", "split": report.get("split"), "scale": scale,
            "sequences": sorted(entry["name"] if isinstance(entry, dict) else str(entry)
                                for entry in report.get("sequences") or []),
            "frame_limit": report.get("frame_limit"),
            "threads": report.get("threads"), "device": report.get("device"), "timing_reference":
                report.get("timing_reference"), "model": brief(row),
            "peers": [brief(entry) for entry in rows if entry.get("method") in PEER_METHODS]}


def ship_checkpoint(checkpoint: str | os.PathLike, name: str, *, root: str | os.PathLike | None = None,
                    dataset_dir: str | os.PathLike | None = None, dataset_script: str | None = None,
                    training_script: str | None = None, report: dict[str, Any] | None = None,
                    report_source: str | None = None, report_path: str | None = None,
                    stages: list[str | os.PathLike] | None = None,
                    after_shipped: str | None = None,
                    **settings: Any) -> PretrainedModel:
    """Write ``root/name/model.pt`` (the checkpoint without optimizer, scheduler and RNG state) and its manifest;
    an existing model of that name is replaced (both files are renamed into place). ``stages``: checkpoints of the
    earlier trainings this one started from (``--init-from``), first to last; their step, best metric and training
    settings are recorded as ``training.stages``. ``after_shipped``: the name of a shipped model (in ``root``) the
    first of them, or this checkpoint, started from (``--init-from pretrained/NAME/model.pt``): its recorded stages
    and its own training come first, so a fine-tune of a shipped model keeps the whole recipe where the earlier
    runs are gone (a fresh checkout holds none). ``settings``: the fused family's run-time settings
    (``RUN_TIME_SETTINGS``) and the seed methods' (``HISTORY_SETTINGS``; None or absent: as the checkpoint
    has them), shipped with the weights unchanged."""
    from model.training.checkpoint import load_checkpoint, save_checkpoint
    from model.methods.registry import build_method, inference_cost

    if not NAME.match(name):
        raise PretrainedError(f"pretrained name {name!r}: use lower-case letters, digits, '.' and '-'")
    content = load_checkpoint(checkpoint)
    config = content["method"]
    method = build_method(f"{config['method']}:{config['preset']}", scale=int(config["scale"]))
    method.load_state_dict(content["model"])
    if not method.learned:
        raise PretrainedError(f"{checkpoint} holds {method.label}, which has no weights to ship")
    known = [*RUN_TIME_SETTINGS, *HISTORY_SETTINGS]
    unknown = sorted(set(settings) - set(known))
    if unknown:
        raise PretrainedError(f"no run-time setting {', '.join(unknown)}; settings: {', '.join(known)}")
    fused = hasattr(method, "set_kernel_max_pixels")
    for setting, value in settings.items():
        if value is None:
            continue
        if setting in HISTORY_SETTINGS:
            if not hasattr(method, f"set_{setting}"):
                raise PretrainedError(f"{checkpoint} holds {method.label}, which has {HISTORY_SETTINGS[setting]} "
                                      f"(only WSKPN, AFN, JNDS and MUNet have)")
        else:
            needs_mean, missing = RUN_TIME_SETTINGS[setting]
            if not fused or (needs_mean and not method.has_mean):
                raise PretrainedError(f"{checkpoint} holds {method.label}, which has {missing} (only the fused "
                                      f"family has)")
        try:
            getattr(method, f"set_{setting}")(value)
        except ValueError as error:
            raise PretrainedError(str(error)) from error
    folder = _root(root) / name
    folder.mkdir(parents=True, exist_ok=True)
    train_config = content.get("train_config") or {}
    best = content.get("best_metric")
    training: dict[str, Any] = {
        "script": training_script, "steps": train_config.get("steps"), "step": int(content["step"]),
        "seed": train_config.get("seed"), "best_metric": best, "train_config": train_config}
    dataset: dict[str, Any] = {"path": train_config.get("data"), "script": dataset_script}
    if dataset_dir is not None:
        dataset.update(dataset_summary(dataset_dir))
    earlier_stages: list[dict[str, Any]] = []
    if after_shipped is not None:
        shipped = get_pretrained(after_shipped, root)
        recorded = shipped.manifest.get("training") or {}
        kept = recorded.get("dataset") or {}
        if dataset_dir is None and kept.get("path") == dataset["path"]:
            # The shipped model's own weights again (a run-time setting changed): its dataset's record stands,
            # which a machine without that dataset could not write again.
            dataset = {**kept, "script": dataset_script or kept.get("script")}
        earlier_stages += list(recorded.get("stages") or [])
        earlier_stages.append({"checkpoint": f"pretrained/{after_shipped}/{shipped.manifest['file']}",
                               "sha256": shipped.manifest["sha256"],
                               "method": {"method": shipped.method, "preset": shipped.manifest["preset"],
                                          "scale": shipped.manifest["scale"]},
                               "step": recorded.get("step"), "best_metric": recorded.get("best_metric"),
                               "train_config": recorded.get("train_config")})
    training["dataset"] = dataset
    if stages or earlier_stages:
        training["stages"] = earlier_stages
        for stage in stages or ():
            earlier = load_checkpoint(stage)
            training["stages"].append({"checkpoint": str(stage), "method": earlier["method"],
                                       "step": int(earlier["step"]), "best_metric": earlier.get("best_metric"),
                                       "train_config": earlier.get("train_config")})
    held_out = {"status": "pending",
                "note": "not evaluated yet: evaluate the checkpoint on the dataset's test split (the reproduction "
                        "script does) and ship it again with that report"}
    if report is not None:
        held_out = held_out_from_report(report, report_source or str(checkpoint), method.name, method.preset,
                                        method.scale)
        held_out["report"] = report_path
    # Written only once every input above was read: a missing stage or a bad report leaves a shipped model as it was.
    weights = save_checkpoint(folder / WEIGHTS, method=method, train_config=train_config, step=content["step"],
                              epoch=content.get("epoch", 0.0), best_metric=best)
    params, flops = inference_cost(method)
    manifest = {"format": PRETRAINED_FORMAT, "name": name, "method": method.name, "preset": method.preset,
                "scale": method.scale, "params": params, "flops_per_pixel": flops, "file": WEIGHTS,
                "sha256": file_sha256(weights), "bytes": weights.stat().st_size, "training": training,
                "held_out": held_out}
    _write_manifest(folder, manifest)
    return get_pretrained(name, root)


def remeasure_shipped(name: str, report: dict[str, Any], report_source: str, report_path: str | None = None,
                      root: str | os.PathLike | None = None) -> PretrainedModel:
    """Replace a shipped model's held-out section with its row (``report_source``) of another evaluation run, such
    as one that also holds newer models; the weights and the training record stay as they are (the file's sha256
    is checked first, so the numbers belong to the file that is there)."""
    shipped = get_pretrained(name, root)
    verify(shipped)
    held_out = held_out_from_report(report, report_source, shipped.method, shipped.preset, shipped.scale)
    held_out["report"] = report_path
    _write_manifest(shipped.folder, {**shipped.manifest, "held_out": held_out})
    return get_pretrained(name, root)


def _write_manifest(folder: Path, manifest: dict[str, Any]) -> None:
    """Renamed into place, so a reader sees the old manifest or the new one whole."""
    temporary = folder / f".{MANIFEST}.{uuid.uuid4().hex[:8]}.tmp"
    temporary.write_text(json.dumps(manifest, indent=2, allow_nan=False) + "\n")
    os.replace(temporary, folder / MANIFEST)
