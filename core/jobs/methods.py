"""Method references in job parameters: checked in the API before queueing, resolved in the worker.

A job names a method the way the CLI does, with one more form:

- ``NAME[:PRESET]`` from the registry (``identity``, ``oidn:high``, ``wskpn:s``);
- ``models:/NAME/VERSION``, ``models:/NAME@ALIAS`` or ``models:/NAME`` (latest): a registered model, whose
  checkpoint ``core.registry.resolve_checkpoint`` brings to local disk;
- the name of a pretrained model shipped in ``pretrained/`` (``fused-balanced-x1``), its sha256 checked;
- a checkpoint file, as a path relative to the data folder (``jobs/<id>/checkpoints/best.pt``). Only files under
  ``jobs/`` and ``models/`` are accepted: a checkpoint is read with ``torch.load``, and an API caller must not be
  able to point the server at arbitrary files.

Every check raises a domain error naming the reference: NotFound for a model or checkpoint that does not exist, Invalid for
an unknown method or preset or a scale the method cannot run at, Unavailable when the model registry is
unreachable.
"""

from __future__ import annotations

from pathlib import Path

from core.errors import DomainError, Invalid, NotFound, Unavailable
from core.storage import Storage

MODEL_REF_PREFIX = "models:/"
CHECKPOINT_SUFFIXES = (".pt", ".pth", ".ckpt")


def is_model_ref(text: str) -> bool:
    return text.startswith(MODEL_REF_PREFIX)


def looks_like_path(text: str) -> bool:
    return "/" in text or text.endswith(CHECKPOINT_SUFFIXES)


def registered_checkpoint(ref: str) -> Path:
    """The local checkpoint of a registered model reference, or NotFound / Invalid / Unavailable."""
    from core import registry

    try:
        return registry.resolve_checkpoint(ref)
    except DomainError:
        raise
    except KeyError as error:  # registry.UnknownModelError
        message = error.args[0] if error.args else str(error)
        raise NotFound("model_not_found", f"model {ref!r}: {message}") from None
    except ValueError as error:
        raise Invalid("invalid_model_ref", f"model {ref!r}: {error}") from None
    except RuntimeError as error:  # registry.RegistryUnavailable
        raise Unavailable("registry_unavailable", f"model {ref!r}: {error}") from None


def checkpoint_in_storage(text: str, storage: Storage) -> Path:
    """A checkpoint path given in a job (relative to the data folder) as an absolute path, or a domain error."""
    root = storage.root.resolve()
    candidate = Path(text)
    path = (candidate if candidate.is_absolute() else root / candidate).resolve()
    allowed = (storage.jobs.resolve(), storage.models.resolve())
    if not any(path.is_relative_to(folder) for folder in allowed):
        raise Invalid("invalid_checkpoint", f"checkpoint {text!r} is outside the data folder's jobs/ and "
                 f"models/; give a path relative to the data folder, e.g. jobs/<id>/checkpoints/best.pt")
    if not path.is_file():
        raise NotFound("checkpoint_not_found", f"checkpoint {text!r} does not exist")
    return path


def pretrained_checkpoint(name: str) -> Path:
    """The verified weights file of a pretrained model, or Invalid when it fails its check."""
    from core.registry import pretrained_dir
    from model.deployment.pretrained import PretrainedError, get_pretrained, verify

    try:
        return verify(get_pretrained(name, pretrained_dir()))
    except PretrainedError as error:
        raise Invalid("invalid_checkpoint", str(error)) from None


def checkpoint_source(text: str, storage: Storage) -> Path | None:
    """The checkpoint file ``text`` stands for, or None when it names a registry method."""
    from core.registry import pretrained_dir
    from model.deployment.pretrained import is_pretrained

    if is_model_ref(text):
        return registered_checkpoint(text)
    if is_pretrained(text, pretrained_dir()):
        return pretrained_checkpoint(text)
    if looks_like_path(text):
        return checkpoint_in_storage(text, storage)
    return None


def checkpoint_method(path: Path, label: str) -> dict:
    """The method config stored in a checkpoint (method, preset, scale), or Invalid for an unreadable one."""
    from model.training.checkpoint import load_checkpoint

    try:
        return load_checkpoint(path)["method"]
    except (ValueError, KeyError, OSError) as error:
        raise Invalid("invalid_checkpoint", f"{label}: {error}") from None


def check_registry_method(text: str, scale: int, *, learned: bool | None = None) -> None:
    """``NAME[:PRESET]`` exists and runs at ``scale`` (and is learned, or not, when asked); else Invalid."""
    from model.methods.registry import method_spec, parse_method_name

    try:
        name, preset = parse_method_name(text)
        spec = method_spec(name)
    except (KeyError, ValueError) as error:
        message = error.args[0] if error.args else str(error)
        raise Invalid("unknown_method", str(message)) from None
    preset = preset or spec.default_preset
    if preset not in spec.presets:
        raise Invalid("unknown_preset", f"method {name!r} has no preset {preset!r}; presets: "
                 f"{', '.join(spec.presets)}")
    if scale not in spec.scales:
        raise Invalid("unsupported_scale", f"method {name!r} does not run at scale {scale}; scales: "
                 f"{', '.join(str(s) for s in spec.scales)}")
    if learned is True and not spec.learned:
        raise Invalid("not_trainable", f"method {name!r} has no trainable parameters; only learned methods "
                 f"train")


def check_method(text: str, scale: int, storage: Storage) -> None:
    """Any method reference a job may evaluate or run, at output ``scale``."""
    path = checkpoint_source(text, storage)
    if path is None:
        check_registry_method(text, scale)
        return
    config = checkpoint_method(path, text)
    if config.get("scale") != scale:
        check_rescalable(text, config, scale)


def check_rescalable(text: str, config: dict, scale: int) -> None:
    # load_method runs a checkpoint at another scale only for methods that denoise at render resolution.
    from model.methods.registry import build_method

    try:
        method = build_method(f"{config['method']}:{config['preset']}", scale=int(config["scale"]))
    except (KeyError, ValueError) as error:
        raise Invalid("invalid_checkpoint", f"{text}: {error}") from None
    if not method.denoises_at_render_resolution:
        raise Invalid("unsupported_scale", f"{text} holds a scale-{config['scale']} {method.label}, which "
                 f"cannot run at scale {scale}")


def runnable(text: str, storage: Storage) -> str:
    """What the model library accepts for ``text``: the registry name, or the checkpoint file's path."""
    path = checkpoint_source(text, storage)
    return text if path is None else str(path)


def build_for_inference(text: str, scale: int | None, storage: Storage):
    """The method ``text`` names, ready for ``step`` in inference (``scale`` None: a checkpoint's own, else 1)."""
    from model.training.checkpoint import load_method
    from model.methods.registry import build_method

    path = checkpoint_source(text, storage)
    method = build_method(text, scale or 1) if path is None else load_method(path, scale=scale)
    return method.for_inference().eval()
