"""The ``evaluate`` and ``benchmark`` jobs' check: the dataset split, and every method at the scale (a benchmark
refuses untrained learned presets); the benchmark's default method list."""

from __future__ import annotations

from typing import Any

from core.errors import Invalid
from core.jobs.checks import open_dataset, split_sequences
from core.jobs.methods import check_method, is_model_ref, looks_like_path
from core.jobs.specs import BenchmarkParams, EvaluateParams
from core.storage import Storage


DEFAULT_BENCHMARK_METHODS = ("identity", "accumulation", "svgf", "oidn:fast", "oidn:balanced", "oidn:high")


def default_methods(scale: int) -> list[str]:
    from model.methods.registry import method_spec, parse_method_name

    return [m for m in DEFAULT_BENCHMARK_METHODS if scale in method_spec(parse_method_name(m)[0]).scales]


def check(params: EvaluateParams, storage: Storage) -> dict[str, Any]:
    dataset = open_dataset(storage, params.dataset)
    split_sequences(dataset, params.dataset, params.split, params.scale)
    methods = list(params.methods if params.methods is not None else default_methods(params.scale))
    benchmark = isinstance(params, BenchmarkParams)
    if benchmark:
        for text in params.include_learned or []:
            if not (is_model_ref(text) or looks_like_path(text)):
                raise Invalid("invalid_request", f"include_learned: {text!r} is not a trained model; give a "
                         "model reference (models:/NAME@ALIAS) or a checkpoint file")
            if text not in methods:
                methods.append(text)
    for method in methods:
        check_method(method, params.scale, storage)
        if benchmark:
            _refuse_untrained(method)
    checked = {**params.model_dump(), "methods": methods}
    if benchmark:
        checked["include_learned"] = None  # merged into methods above
    return checked


def _refuse_untrained(text: str) -> None:
    """A benchmark runs learned methods only from trained weights: a registry name of one would be untrained."""
    from model.methods.registry import method_spec, parse_method_name

    if is_model_ref(text) or looks_like_path(text):
        return
    name = parse_method_name(text)[0]
    if method_spec(name).learned:
        raise Invalid("untrained_method", f"method {text!r} is learned and a registry preset has no trained "
                 f"weights; benchmark a model reference (models:/NAME@ALIAS) or a checkpoint instead")
