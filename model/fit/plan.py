"""A fit's settings and its plan: everything checked before any training (family, presets, target, data,
training settings), each preset's cost, and the fit key under which trained presets are found again
(docs/fit.md, "Reuse")."""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
from pydantic import Field

from model.fit.choice import Candidate
from model.fit.target import DEFAULT_TIMING_RESOLUTION, Target
from model.names import TRAIN_DEVICES
from model.evaluation.timing import TIMING_FRAMES, TIMING_WARMUP
from model.training.training_settings import FitTrainingSettings

DEFAULT_ALIAS = "fitted"
# Settings that do not change the trained weights (or are the preset itself) stay out of the fit key.
KEY_EXCLUDED = ("method", "data", "out", "resume", "device", "world_size", "checkpoint_every", "validate_every",
                "validation_frames", "threads", "tracking_uri", "experiment", "register_as")
# The key hashes these settings under the names they had before the options were declared once
# (model.training.training_settings), so the presets trained by earlier fits are still found.
KEY_NAMES = {"crop": "crop_size", "batch": "batch_size"}
ALIAS_PATTERN = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]{0,254}$")


def dataset_fingerprint(root: str | Path, splits: tuple[str, ...]) -> str:
    """A hash of the manifests of the dataset and of its sequences in ``splits`` (names, frames, cuts, sizes)."""
    from model.io.dataset import MANIFEST, Dataset

    dataset = Dataset(root)
    digest = hashlib.sha256()
    for split in splits:
        for sequence in dataset.sequences(split):
            digest.update(f"{split}/{sequence.name}\n".encode())
            digest.update((Path(sequence.path) / MANIFEST).read_bytes())
    return digest.hexdigest()


def training_key(train_config: dict[str, Any], family: str, fingerprint: str) -> str:
    """The fit key: the settings that shape the trained weights (not the preset) and the data's fingerprint."""
    values = {KEY_NAMES.get(key, key): value for key, value in train_config.items() if key not in KEY_EXCLUDED}
    values.update(family=family, data=fingerprint)
    return hashlib.sha256(json.dumps(values, sort_keys=True, default=str).encode()).hexdigest()[:16]


class FitConfig(FitTrainingSettings):
    """A fit's settings: the training options of every preset (``FitTrainingSettings``, declared once in
    ``model.training.training_settings``), the ladder, the target, and where the fit runs."""

    family: str = Field(min_length=1, description="a learned registry method, without a preset")
    data: str = Field(min_length=1, description="dataset folder")
    target: str = Field(min_length=1, description="see Target.parse")
    presets: list[str] | None = Field(None, description="none: the family's presets without a variant suffix "
                                                        "(\"xs\", not \"xs-int8\")")
    time_at: tuple[int, int] = DEFAULT_TIMING_RESOLUTION  # (width, height) when the target is not ms
    timing_frames: int = TIMING_FRAMES
    timing_warmup: int = TIMING_WARMUP
    device: Literal[TRAIN_DEVICES] = "auto"
    out: str = "runs/fit"
    alias: str = DEFAULT_ALIAS
    tracking_uri: str | None = None

    @property
    def registered_name(self) -> str:
        return self.register_as or f"{self.family}-fit-x{self.scale}"

    def train_config(self, preset: str, out: Path | str, register: bool):
        from model.training.train import TrainConfig

        training = self.model_dump(include=set(FitTrainingSettings.model_fields))
        training.update(method=f"{self.family}:{preset}", data=self.data, out=str(out), resume=True,
                        device=self.device, validate_every=0, tracking_uri=self.tracking_uri,
                        register_as=self.registered_name if register else None)
        return TrainConfig(**training)


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
    from model.io.dataset import Dataset
    from model.methods.registry import build_method, inference_cost, method_spec, parse_method_name
    from model.training.train import prepare, resolve_device

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
    if config.timing_frames < 1:
        raise ValueError(f"timing_frames must be at least 1, got {config.timing_frames}")
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
