"""Command-line options generated from a pydantic model's fields, so an option has the field's name, default, help
and checks (``--frames-per-sample`` for ``frames_per_sample``; ``Field(ge=1)`` refuses ``--frames-per-sample 0``
at parse time, exit status 2, naming the option).

- ``Literal[...]`` fields become ``choices``; ``bool`` fields ``--name / --no-name``; ``int``, ``float`` and ``str``
  fields (optional ones included) are parsed and checked against the field's constraints; ``list[...]`` of those
  take one or more values, repeated or comma-separated (``--scales 1,2``, ``--methods a --methods b``).
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
    on the command line; ``aliases``: extra option strings (old spellings; for a ``bool`` field, one starting with
    ``--no-`` sets it false); ``overrides``: extra or replaced ``add_argument`` keyword arguments per field (a
    metavar, a type that checks more, a form for a field type with none of its own)."""
    excluded, aliases, overrides = set(exclude), aliases or {}, overrides or {}
    unknown = (excluded | set(aliases) | set(overrides)) - set(model.model_fields)
    if unknown:
        raise ValueError(f"{model.__name__} has no field {', '.join(sorted(unknown))}")
    groups = {}
    for names in exclusive:
        group = parser.add_mutually_exclusive_group()
        groups.update(dict.fromkeys(names, group))
    for name, field in model.model_fields.items():
        if name in excluded:
            continue
        kwargs = _argument(name, field, overrides.get(name, {}))
        strings = list(aliases.get(name, ()))
        negative = [s for s in strings if s.startswith("--no-")] if kwargs.get("action") is _BOOL else []
        if negative:
            kwargs["help"] += f" ({', '.join(negative)}: the same as --no-{option_name(name)[2:]})"
        target = groups.get(name, parser)
        target.add_argument(option_name(name), *[s for s in strings if s not in negative], **kwargs)
        for text in negative:  # apart: in the BooleanOptionalAction it would also get a "--no-no-..." twin
            target.add_argument(text, dest=name, action="store_const", const=False, default=argparse.SUPPRESS,
                                help=argparse.SUPPRESS)


# A local command reads a dataset folder (--data, --out), not a stored dataset: when it builds a job kind's
# parameters, the required dataset id gets this stand-in.
FOLDER_DATASET = "folder"


def params_from_args(model: type[BaseModel], args: argparse.Namespace, **values: Any) -> Any:
    """A job kind's parameters as a local command runs them: ``settings_from_args`` with the dataset id filled."""
    return settings_from_args(model, args, **{"dataset": FOLDER_DATASET, **values})


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


_BOOL = argparse.BooleanOptionalAction
_METAVARS = {int: "N", float: "X"}


def _argument(name: str, field, override: dict[str, Any]) -> dict[str, Any]:
    annotation, optional = _unwrap(field.annotation)
    kwargs: dict[str, Any] = {"dest": name, "default": argparse.SUPPRESS, "required": field.is_required()}
    override = dict(override)
    help_text = override.pop("help", None) or field.description or ""  # the model's default is shown either way
    spelled = override.pop("shown_default", None)  # the default as the command's own form of the field spells it
    if not field.is_required() and field.default is not None and field.default is not False:
        shown = field.default if not isinstance(field.default, bool) else ("yes" if field.default else "no")
        if isinstance(shown, list):
            shown = ",".join(str(value) for value in shown)
        help_text += f" (default: {spelled or shown})"
    kwargs["help"] = help_text.replace("%", "%%")
    if {"type", "action"} & set(override):  # the command's own form of the field
        pass
    elif typing.get_origin(annotation) is Literal:
        choices = typing.get_args(annotation)
        kwargs.update(choices=choices, type=_choice(choices))
    elif annotation is bool:
        kwargs["action"] = _BOOL
    elif annotation in (int, float, str):
        kwargs["type"] = _checked(name, annotation, field.metadata)
        kwargs["metavar"] = _METAVARS.get(annotation, name.upper())
    elif typing.get_origin(annotation) is list and _item_parser(name, typing.get_args(annotation)[0]) is not None:
        item = typing.get_args(annotation)[0]
        choices = typing.get_args(item) if typing.get_origin(item) is Literal else None
        kwargs.update(nargs="+", action=_ExtendItems, item=_item_parser(name, item), item_choices=choices,
                      metavar="{" + ",".join(map(str, choices)) + "}" if choices else
                      _METAVARS.get(item, name.upper().rstrip("S")))
    else:
        raise TypeError(f"field {name!r}: no command-line form for {field.annotation}")
    kwargs.update(override)
    return kwargs


def _choice(choices: tuple) -> Any:
    """The argparse ``type`` of a Literal: the choice the text spells (argparse then names a wrong one)."""
    def parse(text: str):
        return next((choice for choice in choices if str(choice) == text), text)

    parse.__name__ = "choice"
    return parse


def _item_parser(name: str, item) -> Any:
    """How one value of a ``list[item]`` field is read, or None when it has no command-line form."""
    if typing.get_origin(item) is Literal:
        choices = typing.get_args(item)

        def parse(text: str):
            value = _choice(choices)(text)
            if value not in choices:
                raise argparse.ArgumentTypeError(f"invalid choice: {text!r} (choose from "
                                                 f"{', '.join(map(str, choices))})")
            return value

        return parse
    if item in (int, float, str):
        return _checked(name, item, ())
    return None


class _ExtendItems(argparse.Action):
    """A list option: every value given, repeated or comma-separated, each read by ``item``."""

    def __init__(self, option_strings, dest, item=None, item_choices=None, **kwargs) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.item = item
        self.item_choices = item_choices  # the Literal's choices, for --help and the options' tests

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        items = list(getattr(namespace, self.dest, None) or [])
        for text in values:
            for part in (p.strip() for p in text.split(",")):
                if not part:
                    continue
                try:
                    items.append(self.item(part))
                except argparse.ArgumentTypeError as error:
                    raise argparse.ArgumentError(self, str(error)) from None
        setattr(namespace, self.dest, items)


def _unwrap(annotation) -> tuple[Any, bool]:
    """``X | None`` -> (X, True); anything else -> (annotation, False)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [arg for arg in typing.get_args(annotation) if arg is not type(None)]
        if len(args) == 1:
            return args[0], True
    return annotation, False


def _checked(name: str, kind: type, metadata):
    """The argparse ``type`` of a field: parse the text as ``kind``, then check the field's constraints."""
    adapter = TypeAdapter(typing.Annotated[kind, *metadata] if metadata else kind)
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
