"""How every command reads a model it is given: a checkpoint file, a registered model (``models:/NAME@ALIAS``,
``models:/NAME/VERSION``, ``models:/NAME``) or a pretrained model's name, the last two through
``core.registry.model_checkpoint`` in the service's registry and pretrained folder, whatever the current folder."""

from __future__ import annotations

from pathlib import Path

from cli.main import UsageError

MODEL_REF_PREFIX = "models:/"
PRETRAINED_SOURCE = "pretrained:"  # how reports name a pretrained model's row (as the model library does)


def model_checkpoint(text: str, option: str, registry=None) -> Path | None:
    """``core.registry.model_checkpoint``, its errors as one line naming ``option`` (exit status 2)."""
    from core.registry import model_checkpoint as resolve

    try:
        return resolve(text, registry)
    except KeyError as error:  # an unknown model, version or alias
        raise UsageError(f"{option} {text}: {error.args[0] if error.args else error}") from None
    except (ValueError, RuntimeError) as error:  # malformed reference, damaged shipped weights, store unreachable
        raise UsageError(f"{option} {text}: {error}") from None


def runnable_method(text: str, option: str) -> tuple[str, str]:
    """(what the model library runs, the source a report names) for a method text: a checkpoint file as given, a
    registered or pretrained model as its weights file, anything else (a method of the registry) as given."""
    if Path(text).is_file():
        return text, text
    path = model_checkpoint(text, option)
    if path is None:
        return text, text
    return str(path), text if text.startswith(MODEL_REF_PREFIX) else PRETRAINED_SOURCE + text


def name_sources(entries: list[dict], methods: list[tuple[str, str]]) -> None:
    """Set each report entry's ``source`` to the model as given (``runnable_method``'s second value), not the
    cached weights file the library ran: one entry per method, in order."""
    for entry, (_, source) in zip(entries, methods, strict=True):
        entry["source"] = source
