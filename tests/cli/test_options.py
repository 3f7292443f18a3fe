"""cli.options: command-line options made from a pydantic model's fields (lists, choices, old spellings)."""

from __future__ import annotations

import argparse

import pytest
from pydantic import BaseModel, Field

from cli.options import FOLDER_DATASET, add_model_options, params_from_args, settings_from_args
from cli.main import UsageError


class Params(BaseModel):
    dataset: str = Field(pattern=r"^[a-z]+$")
    methods: list[str] = Field(min_length=1, description="methods to run")
    scales: list[int] = Field([1, 2], description="scales")
    scale: int | str = 1
    mode: str = "fast"
    level: int = Field(1, ge=1)
    size: list[int] = Field([8, 8], description="size")
    timing: bool = Field(True, description="time it")


def parser_for(**kwargs) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(exit_on_error=False)
    add_model_options(parser, Params, exclude=("dataset", "scale"), **kwargs)
    return parser


def test_a_list_takes_values_repeated_comma_separated_or_several_at_once():
    parser = parser_for(aliases={"methods": ("--method",)})
    args = parser.parse_args(["--method", "a", "--methods", "b,c", "d", "--scales", "4,2"])
    assert args.methods == ["a", "b", "c", "d"] and args.scales == [4, 2]
    params = params_from_args(Params, args)
    assert params.dataset == FOLDER_DATASET and params.size == [8, 8] and params.timing
    with pytest.raises(argparse.ArgumentError, match="expected an integer, got 'x'"):
        parser.parse_args(["--methods", "a", "--scales", "1,x"])


def test_list_items_of_a_literal_are_choices():
    from typing import Literal

    class Choosing(BaseModel):
        scales: list[Literal[1, 2, "both"]] = [1]
        scale: Literal[1, 2, "both"] = 1

    parser = argparse.ArgumentParser(exit_on_error=False)
    add_model_options(parser, Choosing)
    args = parser.parse_args(["--scales", "both,2", "--scale", "both"])
    assert args.scales == ["both", 2] and args.scale == "both"
    with pytest.raises(argparse.ArgumentError, match="invalid choice: '3'"):
        parser.parse_args(["--scales", "3"])
    with pytest.raises(argparse.ArgumentError, match="invalid choice"):
        parser.parse_args(["--scale", "3"])


def test_an_old_negative_spelling_of_a_flag_sets_it_false():
    parser = parser_for(aliases={"timing": ("--no-old-timing",)})
    assert parser.parse_args(["--methods", "a", "--no-old-timing"]).timing is False
    assert parser.parse_args(["--methods", "a", "--no-timing"]).timing is False
    assert parser.parse_args(["--methods", "a", "--timing"]).timing is True
    assert "--no-no-old-timing" not in parser.format_help()
    assert "(--no-old-timing: the same as --no-timing)" in " ".join(parser.format_help().split())


def test_overrides_give_a_field_its_own_form_and_default_text():
    parser = parser_for(overrides={"size": {"type": lambda text: [int(text)] * 2, "metavar": "N",
                                            "shown_default": "8x8", "help": "square side"}})
    assert parser.parse_args(["--methods", "a", "--size", "5"]).size == [5, 5]
    assert "square side (default: 8x8)" in " ".join(parser.format_help().split())


def test_checks_apply_at_parse_time_and_when_the_model_is_built():
    parser = parser_for()
    with pytest.raises(argparse.ArgumentError, match="greater than or equal to 1"):
        parser.parse_args(["--methods", "a", "--level", "0"])
    with pytest.raises(UsageError, match="--dataset: String should match pattern"):
        settings_from_args(Params, parser.parse_args(["--methods", "a"]), dataset="A")


def test_a_misnamed_field_or_one_without_a_form_is_refused():
    with pytest.raises(ValueError, match="has no field method"):
        parser_for(aliases={"method": ("--m",)})
    with pytest.raises(TypeError, match="field 'scale': no command-line form"):
        add_model_options(argparse.ArgumentParser(), Params, exclude=("dataset",))
