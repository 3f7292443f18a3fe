"""Command-line options generated from a pydantic model's fields, so an option has the field's name, default, help
and checks (``--frames-per-sample`` for ``frames_per_sample``; ``Field(ge=1)`` refuses ``--frames-per-sample 0``
at parse time, exit status 2, naming the option).

- ``Literal[...]`` fields become ``choices``; ``bool`` fields ``--name / --no-name``; ``int``, ``float`` and ``str``
  fields (optional ones included) are parsed and checked against the field's constraints.
- Options not given stay out of the parsed namespace (``argparse.SUPPRESS``), so the model's own defaults and its
  cross-field checks (``model_validator``) apply to what was not given; ``settings_from_args`` builds the model.
"""

from __future__ import annotations

import argparse
import math
import types
import typing
from collections.abc import Iterable
from typing import Any, Literal

from pydantic import BaseModel, TypeAdapter, ValidationError

from cli.main import UsageError


def option_name(field: str) -> str:
    return "--" + field.replace("_", "-")


def add_model_options(parser: argparse.ArgumentParser, model: type[BaseModel], *, exclude: Iterable[str] = (),
                      exclusive: Iterable[tuple[str, ...]] = (), aliases: dict[str, tuple[str, ...]] | None = None,
                      overrides: dict[str, dict[str, Any]] | None = None) -> None:
    """One option per field of ``model`` but ``exclude``. ``exclusive``: groups of fields that exclude each other
    on the command line; ``aliases``: extra option strings (old spellings); ``overrides``: extra or replaced
    ``add_argument`` keyword arguments per field (a metavar, a type that checks more)."""
    excluded, aliases, overrides = set(exclude), aliases or {}, overrides or {}
    groups = {}
    for names in exclusive:
        group = parser.add_mutually_exclusive_group()
        groups.update(dict.fromkeys(names, group))
    for name, field in model.model_fields.items():
        if name in excluded:
            continue
        kwargs = _argument(name, field)
        kwargs.update(overrides.get(name, {}))
        groups.get(name, parser).add_argument(option_name(name), *aliases.get(name, ()), **kwargs)


def settings_from_args(model: type[BaseModel], args: argparse.Namespace, **values: Any) -> Any:
    """``model`` built from the options of its fields that were given, and ``values``; a problem raises
    UsageError naming the option."""
    given = {name: getattr(args, name) for name in model.model_fields if hasattr(args, name)}
    try:
        return model(**{**given, **values})
    except ValidationError as error:
        raise UsageError(describe(error)) from None


def describe(error: ValidationError) -> str:
    """A ValidationError as one line per problem, each naming its option (``--crop: ...``)."""
    lines = []
    for problem in error.errors():
        message = problem["msg"].removeprefix("Value error, ")
        where = ".".join(str(part) for part in problem["loc"])
        lines.append(f"{option_name(where)}: {message}" if where else message)
    return "; ".join(lines)


def _argument(name: str, field) -> dict[str, Any]:
    annotation, optional = _unwrap(field.annotation)
    kwargs: dict[str, Any] = {"dest": name, "default": argparse.SUPPRESS, "required": field.is_required()}
    help_text = field.description or ""
    if not field.is_required() and field.default is not None and field.default is not False:
        shown = field.default if not isinstance(field.default, bool) else ("yes" if field.default else "no")
        help_text += f" (default: {shown})"
    kwargs["help"] = help_text.replace("%", "%%")
    if typing.get_origin(annotation) is Literal:
        choices = typing.get_args(annotation)
        kwargs.update(choices=choices, type=type(choices[0]))
    elif annotation is bool:
        kwargs["action"] = argparse.BooleanOptionalAction
    elif annotation in (int, float, str):
        kwargs["type"] = _checked(name, annotation, field)
        kwargs["metavar"] = {int: "N", float: "X", str: name.upper()}[annotation]
    else:
        raise TypeError(f"field {name!r}: no command-line form for {field.annotation}")
    return kwargs


def _unwrap(annotation) -> tuple[Any, bool]:
    """``X | None`` -> (X, True); anything else -> (annotation, False)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [arg for arg in typing.get_args(annotation) if arg is not type(None)]
        if len(args) == 1:
            return args[0], True
    return annotation, False


def _checked(name: str, kind: type, field):
    """The argparse ``type`` of a field: parse the text as ``kind``, then check the field's constraints."""
    adapter = TypeAdapter(typing.Annotated[kind, *field.metadata] if field.metadata else kind)
    expected = {int: "an integer", float: "a number", str: "a text"}[kind]

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
        if kind is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        try:
            return adapter.validate_python(value)
        except ValidationError as error:
            raise argparse.ArgumentTypeError(f"{error.errors()[0]['msg']}, got {text!r}") from None

    parse.__name__ = name  # argparse names the type in some messages
    return parse
