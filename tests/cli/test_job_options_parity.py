"""Each job kind is declared once (core.jobs.kinds.KINDS): its local command's options are its REST parameters'
fields with the same names, defaults and choices, and the REST body of each kind takes exactly those parameters."""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import types
import typing
from pathlib import Path
from typing import Literal

import pytest
from fastapi import FastAPI
from pydantic import BaseModel

from cli.main import build_parser
from cli.options import add_model_options, option_name
from core.jobs.kinds import KINDS
from service.http.routes import jobs as jobs_routes
from service.http.schemas.jobs import JOB_CREATE

FOLDER = "`--data DIR`, a dataset folder"
LOCAL_RUN = "a local run writes its report into files, not to MLflow"
# kind -> (its command, {a field of its parameters the command fills itself: how}). Nothing else may be missing.
COMMANDS = {
    "generate": ("generate", {"dataset": "`--out DIR`, a dataset folder"}),
    "train": ("train", {"dataset": FOLDER, "nodes": "a local training runs on this machine"}),
    "fit": ("fit", {"dataset": FOLDER}),
    "evaluate": ("evaluate", {"dataset": FOLDER, "track": LOCAL_RUN}),
    "benchmark": ("benchmark", {"dataset": FOLDER, "track": LOCAL_RUN}),
    "infer": ("infer", {"dataset": FOLDER}),
    "stability": ("stability", {"dataset": "`--data DIR`, a dataset folder, or `--generate`", "track": LOCAL_RUN}),
}


def subparser(command: str) -> argparse.ArgumentParser:
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return commands.choices[command]


def options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """The options by destination; an old spelling with its own action (``--no-oidn``) is left out."""
    found: dict[str, argparse.Action] = {}
    for action in parser._actions:
        if action.option_strings and action.help != argparse.SUPPRESS:
            found.setdefault(action.dest, action)
    return found


def literal_choices(annotation) -> tuple | None:
    """The choices of ``Literal[...]``, ``Literal[...] | None`` or ``list[Literal[...]]`` (| None)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        annotation = next(a for a in typing.get_args(annotation) if a is not type(None))
    if typing.get_origin(annotation) is list:
        annotation = typing.get_args(annotation)[0]
    return typing.get_args(annotation) if typing.get_origin(annotation) is Literal else None


def mismatches(parser: argparse.ArgumentParser, model: type[BaseModel], filled: dict[str, str]) -> list[str]:
    """Every way the parser's options differ from the model's fields (names, required, choices), ``filled`` aside."""
    found, problems = options(parser), []
    for name, field in model.model_fields.items():
        if name in filled:
            if name in found:
                problems.append(f"{name}: filled by the command, yet an option too")
            continue
        action = found.get(name)
        if action is None or option_name(name) not in action.option_strings:
            problems.append(f"{name}: no option {option_name(name)}")
            continue
        if action.required != field.is_required():
            problems.append(f"{name}: required {action.required}, the field {field.is_required()}")
        if action.default is not argparse.SUPPRESS:  # an option not given must leave the model's default
            problems.append(f"{name}: the option has a default of its own, {action.default!r}")
        choices = literal_choices(field.annotation)
        given = getattr(action, "item_choices", None) or action.choices
        if choices is not None and tuple(given or ()) != choices:
            problems.append(f"{name}: choices {given}, the field's {choices}")
    return problems


def test_every_kind_has_a_command():
    assert set(COMMANDS) == set(KINDS)


@pytest.mark.parametrize("kind", list(KINDS))
def test_each_parameter_is_an_option_of_the_same_name_and_choices(kind):
    command, filled = COMMANDS[kind]
    assert set(filled) <= set(KINDS[kind].params.model_fields)
    assert mismatches(subparser(command), KINDS[kind].params, filled) == []


def required_argv(parser: argparse.ArgumentParser, model: type[BaseModel], values: dict, folder: str) -> list[str]:
    """Options for what the command requires: the model's fields from ``values``, folders for the rest."""
    argv = []
    for action in parser._actions:
        if not action.required or not action.option_strings:
            continue
        if action.dest in model.model_fields:
            value = values[action.dest]
            argv += [action.option_strings[0], *map(str, value if isinstance(value, list) else [value])]
        else:
            argv += [action.option_strings[0], folder]
    for group in parser._mutually_exclusive_groups:
        if group.required:
            argv += [group._group_actions[0].option_strings[0], folder]
    return argv


@pytest.mark.parametrize("kind", list(KINDS))
def test_options_not_given_run_with_the_parameters_defaults(kind, tmp_path):
    """What the command runs with, given only what it requires, is what the API fills in for the same body."""
    command, filled = COMMANDS[kind]
    model = KINDS[kind].params
    parser = subparser(command)
    example = model.model_config["json_schema_extra"]["examples"][0]
    values = {name: example[name] for name, field in model.model_fields.items() if field.is_required()}
    args = build_parser().parse_args([command, *required_argv(parser, model, values, str(tmp_path))])
    module = sys.modules[args.run.__module__]
    ran = module.job_params(args)  # the parameters the command's run uses
    assert type(ran) is model
    expected = model.model_validate(values)
    for name in model.model_fields:
        if name not in filled:
            assert getattr(ran, name) == getattr(expected, name), name


def test_a_field_the_command_lacks_is_found():
    class Params(BaseModel):
        dataset: str
        frames: int = 4
        split: Literal["train", "test"] = "test"

    parser = argparse.ArgumentParser()
    add_model_options(parser, Params, exclude=("dataset",))
    assert mismatches(parser, Params, {"dataset": "--data"}) == []
    parser = argparse.ArgumentParser()
    add_model_options(parser, Params, exclude=("dataset", "frames", "split"))
    parser.add_argument("--split", choices=("train", "test", "all"), default="test")
    assert mismatches(parser, Params, {"dataset": "--data"}) == [
        "frames: no option --frames", "split: the option has a default of its own, 'test'",
        "split: choices ('train', 'test', 'all'), the field's ('train', 'test')"]


def test_the_rest_bodies_take_the_tables_parameters():
    assert set(JOB_CREATE) == set(KINDS)
    for name, body in JOB_CREATE.items():
        assert body.model_fields["params"].annotation is KINDS[name].params
    app = FastAPI()
    app.include_router(jobs_routes.router)
    document = app.openapi()
    schemas = document["components"]["schemas"]
    body = document["paths"]["/jobs"]["post"]["requestBody"]["content"]["application/json"]["schema"]
    refs = {item["$ref"].rsplit("/", 1)[-1] for item in body["oneOf"]}
    assert refs == {f"{name.capitalize()}JobCreate" for name in KINDS}
    for name, kind in KINDS.items():
        params = schemas[f"{name.capitalize()}JobCreate"]["properties"]["params"]["$ref"]
        assert params == f"#/components/schemas/{kind.params.__name__}"
        assert set(schemas[kind.params.__name__]["properties"]) == set(kind.params.model_fields)


def test_each_kind_names_a_check_and_a_run_module_that_exist():
    for kind in KINDS.values():
        assert callable(importlib.import_module(kind.check).check), kind.name
        assert callable(importlib.import_module(kind.run).run), kind.name


# ------------------------------------------------------------------------------------------------ docs

def parameter_table(kind: str) -> list[str]:
    """The Markdown table of a kind's parameters as docs/jobs.md shows it: field, option, default, meaning."""
    command, filled = COMMANDS[kind]
    found = options(subparser(command))
    aliases = {action.dest: [s for s in action.option_strings if s != option_name(action.dest)]
               for action in subparser(command)._actions if action.option_strings}
    lines = ["| field | `denoiser " + command + "` | default | meaning |", "|---|---|---|---|"]
    for name, field in KINDS[kind].params.model_fields.items():
        if name in filled:
            option = f"none ({filled[name]})"
        else:
            option = ", ".join(f"`{s}`" for s in found[name].option_strings + [
                s for s in aliases[name] if s not in found[name].option_strings])
        default = "required" if field.is_required() else f"`{json.dumps(field.default)}`"
        meaning = (field.description or "").replace("|", "\\|")
        lines.append(f"| `{name}` | {option} | {default} | {meaning} |")
    return lines


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_job_guide_lists_every_parameter_with_its_option_and_default(kind):
    guide = (Path(__file__).resolve().parents[2] / "docs" / "jobs.md").read_text()
    assert "\n".join(parameter_table(kind)) in guide, f"regenerate {kind}'s table: parameter_table({kind!r})"
