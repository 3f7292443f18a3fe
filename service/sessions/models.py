"""What a session's ``model`` names, and how its method is built: a registered model, a pretrained one, or a method.

The same names ``denoiser evaluate`` takes, resolved in this order:

- ``NAME:PRESET`` (``oidn:high``): a method of the registry (``model.methods.registry``). Registered model names
  cannot hold ':', so this form is never a registered model;
- a registered model (MLflow: ``version``, ``alias`` or its latest version), which a bare name is first;
- a pretrained model shipped in the repository (``model.deployment.pretrained``; ``denoiser pretrained`` lists them);
- a bare method name (``svgf``, ``oidn-taa``, ``accumulation``) at its default preset.

Only methods without weights run by name: a learned one (``wskpn:s``) would run untrained, so it is refused (422
``untrained_method``) pointing at the trained and pretrained models. A name that is none of these is 404 listing
what exists; a malformed one ('/', two ':', an empty part, surrounding spaces, control characters) is 422
``invalid_model_name``. ``version`` and ``alias`` go with registered models only; ``scale`` picks a method's output
scale (default 1) and, for a model, must be the model's.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import torch

from model.deployment.inference_forms import FormTable, with_inference_forms
from model.methods.base import Method
from core.registry import Registry, UnknownModelError, pretrained_dir

REGISTERED, PRETRAINED, METHOD = "registered", "pretrained", "method"
SOURCES = (REGISTERED, PRETRAINED, METHOD)
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


class SessionModelNotFound(UnknownModelError):
    """The name is no registered model, pretrained model or method (404; ``details`` lists those that exist)."""

    def __init__(self, message: str, details: dict | None = None) -> None:
        super().__init__(message)
        self.details = details


class SessionModelInvalid(ValueError):
    """A malformed name, an untrained method, or options that do not fit the model (422)."""

    def __init__(self, message: str, code: str = "invalid_model_name", details: dict | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.details = details


@dataclass(frozen=True)
class SessionModelSource:
    """Where a session's method comes from; ``version`` is the registered version, the pretrained file's sha256
    prefix, or None for a method (it has no weights)."""

    source: str
    name: str
    version: str | None
    scale: int

    @property
    def key(self) -> tuple:
        """Sessions with the same key share one loaded method."""
        return (self.source, self.name, self.version, self.scale if self.source == METHOD else None)


def check_model_name(name: str) -> None:
    """SessionModelInvalid for a name no model or method can have."""
    problem = None
    if name != name.strip():
        problem = "it starts or ends with spaces"
    elif _CONTROL.search(name):
        problem = "it holds control characters"
    elif "/" in name:
        problem = "it holds '/' (a model reference such as models:/NAME@ALIAS goes to jobs; here give NAME and alias)"
    elif name.count(":") > 1 or name.startswith(":") or name.endswith(":"):
        problem = "a method is NAME or NAME:PRESET, with one ':' between two non-empty parts"
    if problem:
        raise SessionModelInvalid(f"model name {name!r} is malformed: {problem}")


def available_models(registry: Registry | None) -> dict[str, list[str]]:
    """What a session can open: registered model names, pretrained names, and methods without weights."""
    from model.methods.registry import all_methods
    from model.deployment.pretrained import pretrained_names

    registered: list[str] = []
    if registry is not None:
        try:
            registered = [model.name for model in registry.list_models()]
        except Exception:  # the listing is advice in an error message; an unreachable store leaves it empty
            registered = []
    methods = [spec.name + ("" if len(spec.presets) == 1 else f"[:{'|'.join(spec.presets)}]")
               for spec in all_methods() if not spec.learned]
    return {"registered": registered, "pretrained": pretrained_names(pretrained_dir()), "methods": methods}


def _not_found(name: str, registry: Registry | None) -> SessionModelNotFound:
    known = available_models(registry)
    listing = "; ".join(f"{kind}: {', '.join(names) or 'none'}" for kind, names in known.items())
    return SessionModelNotFound(f"model {name!r} does not exist: it is no registered model, pretrained model or "
                                f"method. Available: {listing}", details=known)


def _is_method(name: str) -> bool:
    from model.methods.registry import method_spec

    try:
        method_spec(name)
    except KeyError:
        return False
    return True


def _method_source(text: str, scale: int | None, registry: Registry | None) -> SessionModelSource:
    from model.methods.registry import method_spec, parse_method_name

    name, preset = parse_method_name(text)
    try:
        spec = method_spec(name)
    except KeyError:
        raise _not_found(text, registry) from None
    preset = preset or spec.default_preset
    if preset not in spec.presets:
        raise SessionModelInvalid(f"method {name!r} has no preset {preset!r}; presets: {', '.join(spec.presets)}",
                                  code="unknown_preset", details={"presets": list(spec.presets)})
    if spec.learned:
        raise SessionModelInvalid(
            f"method {name}:{preset} is learned and has no weights by name (it would run untrained); open a session "
            f"on a trained model (GET /models) or a pretrained one (denoiser pretrained)", code="untrained_method",
            details={"untrained": f"{name}:{preset}", **available_models(registry)})
    scale = scale or 1
    if scale not in spec.scales:
        raise SessionModelInvalid(f"method {name!r} does not run at scale {scale}; scales: "
                                  f"{', '.join(str(s) for s in spec.scales)}", code="unsupported_scale")
    return SessionModelSource(METHOD, f"{name}:{preset}", None, scale)


def _fixed_scale(name: str, model_scale: int | None, scale: int | None) -> None:
    if scale is not None and model_scale is not None and scale != model_scale:
        raise SessionModelInvalid(f"model {name!r} runs at scale {model_scale}; scale {scale} is for methods only "
                                  f"(or give no scale)", code="unsupported_scale")


def resolve_session_model(name: str, registry: Registry, version: str | None = None, alias: str | None = None,
                          scale: int | None = None) -> SessionModelSource:
    """The session model ``name`` stands for (module notes), or the error saying why none."""
    from model.deployment.pretrained import get_pretrained, is_pretrained

    check_model_name(name)
    root = pretrained_dir()
    if ":" in name:
        if version is not None or alias is not None:
            raise SessionModelInvalid(f"{name!r} is a method: version and alias go with registered models only",
                                      code="invalid_request")
        return _method_source(name, scale, registry)
    try:
        info = registry.resolve_version(name, version, alias)
    except UnknownModelError:
        if registry.has_model(name):
            raise  # the model exists; its version or alias does not (the message says which)
        if version is not None or alias is not None:
            if is_pretrained(name, root):
                raise UnknownModelError(f"model {name!r} does not exist in the registry (it is a pretrained model: "
                                        f"register the pretrained models with 'denoiser pretrained --register', or "
                                        f"give no version and alias)") from None
            if _is_method(name):
                raise SessionModelInvalid(f"{name!r} is a method: version and alias go with registered models only",
                                          code="invalid_request") from None
            raise _not_found(name, registry) from None
        if is_pretrained(name, root):
            pretrained = get_pretrained(name, root)
            _fixed_scale(name, pretrained.scale, scale)
            return SessionModelSource(PRETRAINED, name, pretrained.sha256[:12], pretrained.scale)
        return _method_source(name, scale, registry)
    _fixed_scale(name, info.scale, scale)
    return SessionModelSource(REGISTERED, info.name, info.version, info.scale or 1)


def registered_checkpoint(source: SessionModelSource, registry: Registry) -> Path | None:
    """A registered source's checkpoint on local disk (downloaded once), None for the others."""
    return registry.checkpoint(source.name, source.version) if source.source == REGISTERED else None


def load_session_method(source: SessionModelSource, checkpoint: Path | None, device: torch.device,
                        forms: FormTable | None = None) -> Method:
    """The source's method in inference form on ``device``, its parameters frozen, its networks run in the form
    ``forms`` measured for each frame's resolution (``checkpoint``: from ``registered_checkpoint``). Raises
    KeyError / ValueError (the checkpoint, the pretrained manifest or file) naming the problem."""
    from model.training.checkpoint import load_method
    from model.methods.registry import build_method
    from model.deployment.pretrained import get_pretrained, load_pretrained

    if source.source == REGISTERED:
        method = load_method(checkpoint, device)
    elif source.source == PRETRAINED:
        root = pretrained_dir()
        if get_pretrained(source.name, root).sha256[:12] != source.version:
            raise ValueError(f"pretrained model {source.name!r} was replaced since this session opened (sha256 "
                             f"{source.version}...); open a new session")
        method = load_pretrained(source.name, device, root=root)
    elif source.source == METHOD:
        method = build_method(source.name, source.scale).to(device).eval()
    else:
        raise ValueError(f"unknown session model source {source.source!r}; known: {', '.join(SOURCES)}")
    method = method.for_inference()
    for parameter in method.parameters():
        parameter.requires_grad_(False)
    return with_inference_forms(method, forms, device)
