"""The training options are declared once (model.training.training_settings): the denoiser train and fit options, the REST
job parameters and the library's configs have the same names, defaults and checks."""

from __future__ import annotations

import argparse

import pytest
from pydantic import BaseModel

from cli.main import build_parser, main
from cli.options import option_name
from core.jobs.specs import FitParams, TrainParams
from model.fit.plan import FitConfig
from model.training.training_settings import (
    NOT_FIT_OPTIONS,
    RUN_FIELDS,
    FitTrainingSettings,
    TrainConfig,
    TrainingSettings,
)

# Fields only the REST parameters have: the stored dataset (the CLI takes a folder, --data) and whether to track
# (the CLI's --track / --no-track, from the job parameters).
REST_ONLY = {"dataset", "track", "nodes"}  # nodes: workers of a job's queue; the local command runs on one machine


def command_options(command: str) -> dict[str, argparse.Action]:
    """The options of ``denoiser COMMAND`` by destination."""
    subparsers = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {action.dest: action for action in subparsers.choices[command]._actions if action.option_strings}


def defaults(model: type[BaseModel], names) -> dict:
    return {name: model.model_fields[name].default for name in names}


def test_the_library_config_is_the_settings_plus_where_the_run_executes():
    assert set(TrainConfig.model_fields) == set(TrainingSettings.model_fields) | set(RUN_FIELDS)
    assert not set(RUN_FIELDS) & set(TrainingSettings.model_fields)
    assert set(FitTrainingSettings.model_fields) == set(TrainingSettings.model_fields) - set(NOT_FIT_OPTIONS)
    training = set(FitTrainingSettings.model_fields)
    assert defaults(FitConfig, training) == defaults(TrainingSettings, training)


def test_rest_train_parameters_are_the_settings_without_the_run_fields():
    assert set(TrainParams.model_fields) == set(TrainingSettings.model_fields) | REST_ONLY
    shared = set(TrainingSettings.model_fields)
    assert defaults(TrainParams, shared) == defaults(TrainingSettings, shared)
    for name in shared:  # the same checks: ranges and choices
        assert TrainParams.model_fields[name].metadata == TrainingSettings.model_fields[name].metadata, name
        assert TrainParams.model_fields[name].annotation == TrainingSettings.model_fields[name].annotation, name


def test_rest_fit_parameters_take_the_fits_training_settings():
    training = set(FitTrainingSettings.model_fields)
    assert training <= set(FitParams.model_fields)
    assert not set(NOT_FIT_OPTIONS) - {"method"} & set(FitParams.model_fields)  # method: the family
    assert defaults(FitParams, training) == defaults(FitTrainingSettings, training)


def test_train_options_are_the_config_fields_with_the_same_names_and_defaults():
    options = command_options("train")
    assert set(TrainConfig.model_fields) <= set(options)
    for name, field in TrainConfig.model_fields.items():
        assert option_name(name) in options[name].option_strings, name
        assert options[name].required == field.is_required(), name
    # Options not given take the model's defaults: what the CLI trains with is TrainConfig's default.
    assert set(options) - set(TrainConfig.model_fields) == {"help", "track", "quiet"}


def test_fit_options_include_every_fit_training_setting():
    options = command_options("fit")
    for name in FitTrainingSettings.model_fields:
        assert option_name(name) in options[name].option_strings, name
    assert "world_size" not in options and "init_from" not in options


def test_the_old_warmup_spelling_still_works():
    assert "--warmup" in command_options("train")["warmup_steps"].option_strings
    assert "--warmup" in command_options("fit")["warmup_steps"].option_strings


@pytest.mark.parametrize("command", ["train", "fit"])
def test_no_tracking_is_still_the_negative_of_track(tmp_path, command):
    from cli.main import build_parser
    from cli.options import params_from_args

    required = ["--method", "wskpn"] + (["--target", "psnr=30"] if command == "fit" else [])
    model = TrainParams if command == "train" else FitParams
    for flag, expected in ((["--no-tracking"], False), (["--no-track"], False), ([], True), (["--track"], True)):
        args = build_parser().parse_args([command, "--data", str(tmp_path), *required, *flag])
        assert params_from_args(model, args).track is expected, flag


@pytest.mark.parametrize("command, argv, words", [
    ("fit", ["--lr", "-1"], "argument --lr: Input should be greater than 0, got '-1'"),
    ("fit", ["--lr", "nan"], "argument --lr: expected a finite number"),
    ("fit", ["--crop", "0"], "argument --crop: Input should be greater than or equal to 1"),
    ("fit", ["--tonemap", "sqrt"], "argument --tonemap: invalid choice"),
    ("train", ["--spatial-weight", "-0.5"], "argument --spatial-weight: Input should be greater than or equal to 0"),
    ("train", ["--loss-skip-frames", "x"], "argument --loss-skip-frames: expected an integer"),
    ("train", ["--epochs", "2", "--steps", "3"], "argument --steps: not allowed with argument --epochs"),
    ("train", ["--seed", "-3"], "argument --seed: Input should be greater than or equal to 0"),
])
def test_an_option_out_of_range_exits_2_naming_it(tmp_path, capsys, command, argv, words):
    required = (["--method", "wskpn", "--target", "psnr=30"] if command == "fit" else ["--method", "wskpn"])
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--data", str(tmp_path), *required, *argv])
    assert exit_info.value.code == 2
    assert words in capsys.readouterr().err


def test_cross_field_checks_exit_2_with_the_settings_message(tmp_path, capsys):
    assert main(["train", "--data", str(tmp_path), "--method", "wskpn", "--frames-per-sample", "2",
                 "--loss-skip-frames", "2"]) == 2
    assert "denoiser train: error: loss_skip_frames (2) must be below frames_per_sample (2)" in capsys.readouterr().err
