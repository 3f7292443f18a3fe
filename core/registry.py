"""The MLflow model registry as the service sees it: models, versions, aliases, and local checkpoints.

Training registers each final checkpoint as a new version of a registered model (``core.tracking``), tagged
with method, preset, scale, params, flops_per_pixel and validation_psnr. This module reads those back, manages
aliases (``champion``, ``staging``, ...: MLflow 3 has no stages), and turns a model reference into a checkpoint
on local disk:

    models:/NAME/VERSION    that version
    models:/NAME@ALIAS      the version the alias points at
    models:/NAME            the latest (highest) version

``choose_auto`` picks a version by those tags (the smallest that meets a PSNR floor, or the best PSNR within a time
budget): what a session created with ``{"model": "auto", ...}`` runs.

Checkpoints are downloaded once into ``storage.model(name, version)`` and reused: a registered version never
changes its files. ``model_checkpoint`` is how every command turns a model text (a reference above, or a pretrained
model's name) into a weights file, in the configured registry and pretrained folder. Errors: ``UnknownModelError``
(a KeyError) for a name, version or alias that does not exist, ValueError for a malformed reference, version or
alias name, ``RegistryUnavailable`` when the tracking store cannot be reached.
"""

from __future__ import annotations

import math
import os
import re
import shutil
import threading
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timezone
from functools import lru_cache
from pathlib import Path

from mlflow.exceptions import MlflowException

from core.names import at_most_pattern
from core.storage import Storage
from core.tracking import CHECKPOINT_ARTIFACT, MLflowTracker, download_registered_checkpoint

# MLflow draws a tqdm bar per checkpoint download, noise in a server log (read at each download).
os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")

MODEL_REF = re.compile(r"^models:/(?P<name>[^/@]+)(?:/(?P<version>[^/@]+)|@(?P<alias>[^/@]+))?$")
# Version tags that hold measurements; everything else in the tags is description.
METRIC_TAGS = ("validation_psnr", "validation_ssim", "ms_per_frame")
METRIC_TAG_PREFIX = "metric."  # any other measurement a job records on a version, e.g. metric.flip
_PAGE = 1000
MAX_VERSION = 2**31 - 1
VERSION_PATTERN = at_most_pattern(MAX_VERSION)  # 1..MAX_VERSION as text, what checked_version accepts


class UnknownModelError(KeyError):
    """A registered model, version or alias that does not exist (the message names which)."""

    def __str__(self) -> str:  # KeyError would print the message quoted
        return str(self.args[0]) if self.args else ""


class RegistryUnavailable(RuntimeError):
    """The tracking store failed for a reason other than the caller's input (down, misconfigured)."""


@dataclass(frozen=True)
class ModelRef:
    name: str
    version: str | None = None
    alias: str | None = None

    @classmethod
    def parse(cls, text: str) -> ModelRef:
        match = MODEL_REF.match(text.strip())
        if match is None:
            raise ValueError(f"{text!r} is not a model reference: use models:/NAME/VERSION, models:/NAME@ALIAS "
                             f"or models:/NAME (latest version)")
        return cls(match["name"], match["version"], match["alias"])

    def __str__(self) -> str:
        if self.version is not None:
            return f"models:/{self.name}/{self.version}"
        if self.alias is not None:
            return f"models:/{self.name}@{self.alias}"
        return f"models:/{self.name}"


@dataclass(frozen=True)
class ModelVersionInfo:
    name: str
    version: str
    run_id: str | None
    created_at: datetime
    method: str | None
    preset: str | None
    scale: int | None
    params: int | None
    flops_per_pixel: float | None
    metrics: dict[str, float]
    tags: dict[str, str]
    aliases: list[str]
    source: str | None


@dataclass(frozen=True)
class RegisteredModelInfo:
    name: str
    description: str | None
    latest_version: str | None
    aliases: dict[str, str]
    created_at: datetime | None
    versions: list[ModelVersionInfo] = field(default_factory=list)


@dataclass(frozen=True)
class ResolvedModel:
    """A model reference pinned to one version, with its checkpoint on local disk."""

    ref: str
    alias: str | None
    info: ModelVersionInfo
    checkpoint: Path


def checked_version(version: str | int) -> str:
    text = str(version).strip()
    if not text.isdigit() or int(text) < 1:
        raise ValueError(f"model version {version!r} is not a positive integer")
    if int(text) > MAX_VERSION:  # the store's integer column would overflow: no such version can exist
        raise ValueError(f"model version {text} is out of range (at most {MAX_VERSION})")
    return str(int(text))


def _timestamp(milliseconds: int | None) -> datetime | None:
    return None if milliseconds is None else datetime.fromtimestamp(milliseconds / 1000, tz=timezone.utc)


def _number(text: str | None, kind: type) -> int | float | None:
    try:
        return None if text is None else kind(float(text)) if kind is int else kind(text)
    except (ValueError, OverflowError):
        return None


class Registry:
    """Registry reads and alias changes against one tracking URI; checkpoints cached under ``storage``."""

    def __init__(self, tracking_uri: str, storage: Storage) -> None:
        self.tracking_uri = tracking_uri
        self.storage = storage
        self._client = None
        self._client_lock = threading.Lock()
        self._download_lock = threading.Lock()

    @property
    def client(self):
        # MLflowTracker's client creates a SQLite store's tables under a file lock (concurrent first use races
        # in MLflow's migrations); the registry reuses that rather than opening the store a second way.
        with self._client_lock:
            if self._client is None:
                try:
                    self._client = MLflowTracker(self.tracking_uri).client
                except Exception as error:
                    raise RegistryUnavailable(f"model registry at {self.tracking_uri} is unavailable: {error}") \
                        from None
            return self._client

    def _call(self, what: str, function, *args, **kwargs):
        """Run one MLflow call, translating its errors into UnknownModelError / ValueError / RegistryUnavailable."""
        try:
            return function(*args, **kwargs)
        except MlflowException as error:
            if error.error_code == "RESOURCE_DOES_NOT_EXIST":
                raise UnknownModelError(f"{what} does not exist") from None
            if error.error_code == "INVALID_PARAMETER_VALUE":
                raise ValueError(f"{what}: {error.message}") from None
            raise RegistryUnavailable(f"model registry error for {what}: {error.message}") from None
        except (UnknownModelError, ValueError):
            raise
        except Exception as error:  # connection failures of a remote store surface as many types
            raise RegistryUnavailable(f"model registry error for {what}: {type(error).__name__}: {error}") from None

    # ------------------------------------------------------------------------------------------ reads

    def list_models(self) -> list[RegisteredModelInfo]:
        models, token = [], None
        while True:
            page = self._call("registered models", self.client.search_registered_models, max_results=_PAGE,
                              page_token=token)
            models.extend(page)
            token = page.token
            if not token:
                break
        return [self._model_info(model, self._versions(model.name)) for model in sorted(models, key=lambda m: m.name)]

    def get_model(self, name: str) -> RegisteredModelInfo:
        model = self._call(f"model {name!r}", self.client.get_registered_model, name)
        return self._model_info(model, self._versions(name), with_versions=True)

    def get_version(self, name: str, version: str | int) -> ModelVersionInfo:
        version = checked_version(version)
        model = self._call(f"model {name!r}", self.client.get_registered_model, name)
        entity = self._call(f"version {version} of model {name!r}", self.client.get_model_version, name, version)
        return self._version_info(entity, model.aliases)

    def has_model(self, name: str) -> bool:
        """Whether a registered model ``name`` exists (False also for a name the store cannot hold)."""
        try:
            self._call(f"model {name!r}", self.client.get_registered_model, name)
        except (UnknownModelError, ValueError):
            return False
        return True

    def latest_version(self, name: str) -> ModelVersionInfo:
        model = self._call(f"model {name!r}", self.client.get_registered_model, name)
        versions = self._versions(name)
        if not versions:
            raise UnknownModelError(f"model {name!r} has no versions")
        return self._version_info(versions[-1], model.aliases)

    # ---------------------------------------------------------------------------------------- aliases

    def get_alias(self, name: str, alias: str) -> ModelVersionInfo:
        model = self._call(f"model {name!r}", self.client.get_registered_model, name)
        if alias not in model.aliases:
            known = ", ".join(sorted(model.aliases)) or "none"
            raise UnknownModelError(f"model {name!r} has no alias {alias!r} (aliases: {known})")
        version = str(model.aliases[alias])
        entity = self._call(f"version {version} of model {name!r}", self.client.get_model_version, name, version)
        return self._version_info(entity, model.aliases)

    def set_alias(self, name: str, alias: str, version: str | int) -> ModelVersionInfo:
        version = checked_version(version)
        self._call(f"model {name!r}", self.client.get_registered_model, name)
        self._call(f"version {version} of model {name!r}", self.client.get_model_version, name, version)
        self._call(f"alias {alias!r} of model {name!r}", self.client.set_registered_model_alias, name, alias, version)
        return self.get_alias(name, alias)

    def delete_alias(self, name: str, alias: str) -> None:
        self.get_alias(name, alias)  # MLflow deletes an unknown alias silently; the API answers 404 for it
        self._call(f"alias {alias!r} of model {name!r}", self.client.delete_registered_model_alias, name, alias)

    # -------------------------------------------------------------------------------------- deletion

    def delete_version(self, name: str, version: str | int) -> None:
        """Delete one version (MLflow drops the aliases that pointed at it) and its cached checkpoint. Sessions
        already open on it keep their weights in memory; new sessions and jobs find it gone."""
        info = self.get_version(name, version)  # 404 for an unknown model or version
        self._call(f"version {info.version} of model {name!r}", self.client.delete_model_version, name, info.version)
        shutil.rmtree(self.storage.model(name, info.version), ignore_errors=True)

    def delete_model(self, name: str) -> None:
        """Delete a registered model with every version and their cached checkpoints."""
        self._call(f"model {name!r}", self.client.get_registered_model, name)  # 404 for an unknown model
        self._call(f"model {name!r}", self.client.delete_registered_model, name)
        shutil.rmtree(self.storage.model_versions(name), ignore_errors=True)

    # ----------------------------------------------------------------------------------- resolution

    def resolve_version(self, name: str, version: str | int | None = None,
                        alias: str | None = None) -> ModelVersionInfo:
        """The version named by ``version``, else by ``alias``, else the latest one."""
        if version is not None and alias is not None:
            raise ValueError(f"give a version or an alias of model {name!r}, not both")
        if version is not None:
            return self.get_version(name, version)
        if alias is not None:
            return self.get_alias(name, alias)
        return self.latest_version(name)

    def resolve(self, ref: str | ModelRef) -> ResolvedModel:
        """A model reference -> that version's info and its checkpoint on local disk (downloaded once)."""
        parsed = ref if isinstance(ref, ModelRef) else ModelRef.parse(ref)
        info = self.resolve_version(parsed.name, parsed.version, parsed.alias)
        return ResolvedModel(ref=str(parsed), alias=parsed.alias, info=info,
                             checkpoint=self.checkpoint(info.name, info.version))

    def checkpoint(self, name: str, version: str | int) -> Path:
        """The local copy of a registered version's checkpoint, downloaded into the cache on first use."""
        version = checked_version(version)
        folder = self.storage.model(name, version)  # ValueError for a name unusable as a folder name
        cached = folder / CHECKPOINT_ARTIFACT
        if cached.is_file():
            return cached
        with self._download_lock:
            if cached.is_file():
                return cached
            # Downloaded to staging and renamed into place, so the cache never holds half a checkpoint (another
            # process racing us may win the rename; its copy is the same file).
            staging = self.storage.staging / f"model-{uuid.uuid4().hex}"
            try:
                self._call(f"checkpoint of version {version} of model {name!r}", download_registered_checkpoint,
                           name, version, staging, tracking_uri=self.tracking_uri)
                if not (staging / CHECKPOINT_ARTIFACT).is_file():
                    raise RegistryUnavailable(f"version {version} of model {name!r} has no {CHECKPOINT_ARTIFACT}")
                folder.parent.mkdir(parents=True, exist_ok=True)
                try:
                    staging.rename(folder)
                except OSError:
                    if not cached.is_file():
                        raise
            finally:
                shutil.rmtree(staging, ignore_errors=True)
        return cached

    # -------------------------------------------------------------------------------------- helpers

    def _versions(self, name: str) -> list:
        """Every version entity of ``name``, ascending by version number."""
        if "'" in name:
            raise ValueError(f"model name {name!r} contains a quote, which registry searches cannot express")
        versions, token = [], None
        while True:
            page = self._call(f"versions of model {name!r}", self.client.search_model_versions,
                              f"name = '{name}'", max_results=_PAGE, page_token=token)
            versions.extend(page)
            token = page.token
            if not token:
                break
        return sorted(versions, key=lambda v: int(v.version))

    def _model_info(self, model, versions: list, with_versions: bool = False) -> RegisteredModelInfo:
        aliases = {alias: str(version) for alias, version in sorted(model.aliases.items())}
        return RegisteredModelInfo(
            name=model.name, description=model.description or None,
            latest_version=str(versions[-1].version) if versions else None, aliases=aliases,
            created_at=_timestamp(model.creation_timestamp),
            versions=[self._version_info(v, model.aliases) for v in versions] if with_versions else [])

    @staticmethod
    def _version_info(entity, aliases: dict) -> ModelVersionInfo:
        tags = dict(entity.tags or {})
        metrics = {}
        for key, value in tags.items():
            if key in METRIC_TAGS or key.startswith(METRIC_TAG_PREFIX):
                number = _number(value, float)
                if number is not None:
                    metrics[key.removeprefix(METRIC_TAG_PREFIX)] = number
        version = str(entity.version)
        return ModelVersionInfo(
            name=entity.name, version=version, run_id=entity.run_id or None,
            created_at=_timestamp(entity.creation_timestamp), method=tags.get("method"), preset=tags.get("preset"),
            scale=_number(tags.get("scale"), int), params=_number(tags.get("params"), int),
            flops_per_pixel=_number(tags.get("flops_per_pixel"), float), metrics=metrics, tags=tags,
            aliases=sorted(alias for alias, target in aliases.items() if str(target) == version),
            source=entity.source or None)


@lru_cache(maxsize=8)
def registry_for(tracking_uri: str, root: Path) -> Registry:
    """One shared Registry per (tracking URI, data folder)."""
    return Registry(tracking_uri, Storage(root).ensure())


def get_registry() -> Registry:
    """The registry of the configured tracking URI and data folder (one per configuration, shared)."""
    from core.settings import get_settings

    settings = get_settings()
    return registry_for(settings.resolved_tracking_uri(), Path(settings.data_dir))


def resolve_checkpoint(ref: str) -> Path:
    """``models:/NAME/VERSION``, ``models:/NAME@ALIAS`` or ``models:/NAME`` -> the checkpoint file on local disk.

    Raises ValueError for a malformed reference, UnknownModelError (KeyError) for an unknown name, version or
    alias, RegistryUnavailable when the tracking store fails.
    """
    return get_registry().resolve(ref).checkpoint


def pretrained_dir() -> Path | None:
    """The configured folder of the shipped models (``Settings.pretrained_dir``; None: the library's default)."""
    from core.settings import get_settings

    return get_settings().pretrained_dir


def model_checkpoint(text: str, registry: Registry | None = None) -> Path | None:
    """The weights file on local disk that a model text names, the same for every entry point and whatever the
    current folder: a registered version (``models:/NAME/VERSION``, ``models:/NAME@ALIAS``, ``models:/NAME``; of
    ``registry``, else the configured one) or a pretrained model of the configured folder (its sha256 checked).
    None for any other text (a checkpoint path or a method name: the caller's to judge).

    Raises ValueError for a malformed reference, UnknownModelError (KeyError) for an unknown model, version or
    alias, RegistryUnavailable when the tracking store fails, ``PretrainedError`` (a ValueError) for shipped
    weights that fail their check.
    """
    from model.deployment.pretrained import get_pretrained, is_pretrained, verify

    if text.startswith("models:/"):
        return resolve_checkpoint(text) if registry is None else registry.resolve(text).checkpoint
    root = pretrained_dir()
    if is_pretrained(text, root):
        return verify(get_pretrained(text, root))
    return None


# =========================================================================================================
# Automatic choice: sessions created with {"model": "auto", ...} (docs/service.md, "Choosing the model: auto")
# =========================================================================================================

_FAMILY = re.compile(r"^[A-Za-z0-9_]+$")


class NoAutoCandidates(UnknownModelError):
    """No registered version carries the measurements an automatic choice needs (answered 404)."""

    def __init__(self, message: str, details: dict | None = None) -> None:
        super().__init__(message)
        self.details = details


class ConstraintNotMet(ValueError):
    """Versions could be compared, but none satisfies the constraint (answered 422); ``details`` names the closest."""

    def __init__(self, message: str, details: dict | None = None) -> None:
        super().__init__(message)
        self.details = details


@dataclass(frozen=True)
class AutoChoice:
    """The version an automatic choice picked, the constraint, and why, in words."""

    info: ModelVersionInfo
    constraint: dict
    reason: str
    candidates: int  # versions that had the measurements to be compared

    def to_dict(self) -> dict:
        info = self.info
        return {"name": info.name, "version": info.version, "method": info.method, "preset": info.preset,
                "scale": info.scale, "flops_per_pixel": info.flops_per_pixel,
                "validation_psnr": info.metrics.get("validation_psnr"),
                "ms_per_frame": info.metrics.get("ms_per_frame"),
                "ms_per_frame_resolution": info.tags.get("ms_per_frame_resolution"),
                "constraint": dict(self.constraint), "candidates": self.candidates, "reason": self.reason}


def _size_key(info: ModelVersionInfo) -> tuple:
    """Smallest first: FLOPs per pixel, parameters, ms per frame (unknown ones last), then name and version."""
    def known(value):
        return math.inf if value is None else value

    return (known(info.flops_per_pixel), known(info.params), known(info.metrics.get("ms_per_frame")), info.name,
            int(info.version))


def _describe_version(info: ModelVersionInfo) -> str:
    label = f"{info.method}:{info.preset}" if info.preset else str(info.method)
    flops = "unknown" if info.flops_per_pixel is None else f"{info.flops_per_pixel:.4g}"
    return f"{info.name} version {info.version} ({label} at scale {info.scale}, {flops} FLOPs/px)"


def _timing_text(info: ModelVersionInfo) -> str:
    resolution = info.tags.get("ms_per_frame_resolution")
    at = f"at {resolution}" if resolution else "at an unrecorded resolution"
    threads = info.tags.get("ms_per_frame_threads")
    return f"{info.metrics['ms_per_frame']:.3g} ms per frame {at}" + (f", {threads} threads" if threads else "")


def check_auto_constraint(max_ms_per_frame: float | None = None, min_psnr: float | None = None,
                          family: str | None = None, scale: int | None = None) -> dict:
    """The constraint as a dict, or ValueError for an empty or malformed one."""
    if max_ms_per_frame is None and min_psnr is None:
        raise ValueError("an automatic model choice needs max_ms_per_frame, min_psnr or both")
    for name, value in (("max_ms_per_frame", max_ms_per_frame), ("min_psnr", min_psnr)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number, got {value!r}")
    if family is not None and not _FAMILY.match(family):
        raise ValueError(f"family {family!r} is not a method family name (letters, digits, _)")
    if scale is not None and scale not in (1, 2):
        raise ValueError(f"scale must be 1 or 2, got {scale!r}")
    return {key: value for key, value in (("max_ms_per_frame", max_ms_per_frame), ("min_psnr", min_psnr),
                                          ("family", family), ("scale", scale)) if value is not None}


def choose_version(versions: list[ModelVersionInfo], max_ms_per_frame: float | None = None,
                   min_psnr: float | None = None, family: str | None = None, scale: int | None = None) -> AutoChoice:
    """Pick among registered versions by their tags (method, scale, flops_per_pixel, validation_psnr,
    ms_per_frame):

    - ``min_psnr``: the smallest version (FLOPs per pixel, then parameters) with validation PSNR >= min_psnr;
    - ``max_ms_per_frame``: the best validation PSNR among versions with ms_per_frame <= the budget (ties: the
      smaller);
    - both: the smallest version that satisfies both.

    Candidates are versions with a ``method`` tag (of ``family``, at ``scale``, when given), a validation PSNR and,
    for a time budget, an ms_per_frame. NoAutoCandidates when there are none, ConstraintNotMet when none passes.
    """
    constraint = check_auto_constraint(max_ms_per_frame, min_psnr, family, scale)
    needed = ["validation_psnr"] + (["ms_per_frame"] if max_ms_per_frame is not None else [])
    candidates = [v for v in versions
                  if v.method and (family is None or v.method == family) and (scale is None or v.scale == scale)
                  and all(name in v.metrics for name in needed)]
    where = "".join([f" of family {family!r}" if family else "", f" at scale {scale}" if scale else ""])
    if not candidates:
        raise NoAutoCandidates(
            f"no registered model version{where} has the tags an automatic choice compares ({', '.join(needed)}); "
            f"'denoiser fit' (or a fit job) records them, or pick a model by name",
            {"constraint": constraint, "needed_tags": needed})
    passing = [v for v in candidates
               if (min_psnr is None or v.metrics["validation_psnr"] >= min_psnr)
               and (max_ms_per_frame is None or v.metrics["ms_per_frame"] <= max_ms_per_frame)]
    if not passing:
        raise ConstraintNotMet(_not_met_message(candidates, constraint, where), _closest(candidates, constraint))
    count = f"{len(passing)} of {len(candidates)} candidate versions{where}"
    if min_psnr is None:
        best = max(v.metrics["validation_psnr"] for v in passing)
        chosen = min((v for v in passing if v.metrics["validation_psnr"] == best), key=_size_key)
        reason = (f"{_describe_version(chosen)}: the best validation PSNR ({best:.2f} dB) of the {count} within "
                  f"{max_ms_per_frame:g} ms per frame ({_timing_text(chosen)})")
    else:
        chosen = min(passing, key=_size_key)
        rule = f"validation PSNR >= {min_psnr:g} dB"
        measured = f"{chosen.metrics['validation_psnr']:.2f} dB"
        if max_ms_per_frame is not None:
            rule += f" and <= {max_ms_per_frame:g} ms per frame"
            measured += f", {_timing_text(chosen)}"
        reason = f"{_describe_version(chosen)}: the smallest of the {count} with {rule} ({measured})"
    return AutoChoice(info=chosen, constraint=constraint, reason=reason, candidates=len(candidates))


def _not_met_message(candidates: list[ModelVersionInfo], constraint: dict, where: str) -> str:
    parts = []
    if "min_psnr" in constraint:
        best = max(candidates, key=lambda v: v.metrics["validation_psnr"])
        parts.append(f"the best validation PSNR is {best.metrics['validation_psnr']:.2f} dB "
                     f"({best.name} version {best.version})")
    if "max_ms_per_frame" in constraint:
        fastest = min(candidates, key=lambda v: v.metrics["ms_per_frame"])
        parts.append(f"the fastest takes {_timing_text(fastest)} ({fastest.name} version {fastest.version})")
    wanted = " and ".join(f"{name} {value:g}" for name, value in constraint.items()
                          if name in ("max_ms_per_frame", "min_psnr"))
    return f"none of the {len(candidates)} candidate versions{where} satisfies {wanted}: {'; '.join(parts)}"


def _closest(candidates: list[ModelVersionInfo], constraint: dict) -> dict:
    details: dict = {"constraint": constraint, "candidates": len(candidates)}
    best = max(candidates, key=lambda v: v.metrics["validation_psnr"])
    fastest = min(candidates, key=lambda v: v.metrics.get("ms_per_frame", math.inf))
    details["best_psnr"] = {"ref": f"models:/{best.name}/{best.version}",
                            "validation_psnr": best.metrics["validation_psnr"]}
    if "max_ms_per_frame" in constraint:
        details["fastest"] = {"ref": f"models:/{fastest.name}/{fastest.version}",
                              "ms_per_frame": fastest.metrics["ms_per_frame"]}
    return details


def all_versions(registry: Registry, family: str | None = None) -> list[ModelVersionInfo]:
    """Every registered version (of ``family``, by its method tag, when given), with its model's aliases."""
    if family is not None and not _FAMILY.match(family):
        raise ValueError(f"family {family!r} is not a method family name (letters, digits, _)")
    query = None if family is None else f"tags.method = '{family}'"
    entities, token = [], None
    while True:
        page = registry._call("model versions", registry.client.search_model_versions, query, max_results=_PAGE,
                              page_token=token)
        entities.extend(page)
        token = page.token
        if not token:
            break
    return [Registry._version_info(entity, {}) for entity in entities]


def choose_auto(max_ms_per_frame: float | None = None, min_psnr: float | None = None, family: str | None = None,
                scale: int | None = None, registry: Registry | None = None) -> AutoChoice:
    """The registered version an automatic choice picks (``choose_version``) from the configured registry (or
    ``registry``). Raises ValueError for a malformed constraint, NoAutoCandidates (404) or ConstraintNotMet (422)."""
    check_auto_constraint(max_ms_per_frame, min_psnr, family, scale)
    registry = registry or get_registry()
    return choose_version(all_versions(registry, family), max_ms_per_frame=max_ms_per_frame, min_psnr=min_psnr,
                          family=family, scale=scale)
