"""The ``evaluate`` and ``benchmark`` jobs' check: the dataset split, and every method at the scale (a benchmark
refuses untrained learned presets); the benchmark's method list and scales, shared with ``denoiser benchmark``."""

from __future__ import annotations

from typing import Any

from core.errors import Invalid
from core.jobs.checks import open_dataset, split_sequences
from core.jobs.methods import check_method, is_model_ref, looks_like_path
from core.jobs.specs import BenchmarkParams, EvaluateParams
from core.settings import Settings
from core.storage import Storage

# OIDN fast / balanced / high, alone and with TAA, are the reference points of every benchmark: a method built on
# OIDN is compared with both at its own OIDN quality.
ALWAYS_ALL_PRESETS = ("oidn", "oidn-taa")


def benchmark_scales(scale: int | str) -> tuple[int, ...]:
    return (1, 2) if scale == "both" else (int(scale),)


def baseline_methods(methods: list[str] | None = None, all_presets: bool = False) -> list[str]:
    """The benchmark's registry methods: ``methods``, or by default every non-learned method at its default preset
    and those of ``ALWAYS_ALL_PRESETS`` at all of theirs; ``all_presets``: every preset of each method not named
    with one. Other texts (model references, checkpoints) pass through; KeyError for an unknown method."""
    from model.methods.registry import all_methods, method_spec, parse_method_name

    def spelled(name: str, preset: str) -> str:
        return name if preset == "default" else f"{name}:{preset}"

    texts: list[str] = []
    if methods is None:
        for spec in all_methods():
            if not spec.learned:
                presets = spec.presets if all_presets or spec.name in ALWAYS_ALL_PRESETS else (spec.default_preset,)
                texts += [spelled(spec.name, preset) for preset in presets]
    else:
        for text in methods:
            if is_model_ref(text) or looks_like_path(text) or ":" in text or not all_presets:
                texts.append(text)
                continue
            spec = method_spec(parse_method_name(text)[0])
            texts += [spelled(spec.name, preset) for preset in spec.presets]
    return list(dict.fromkeys(texts))  # in order, once each


def default_methods(scale: int) -> list[str]:
    """The default benchmark methods that run at ``scale``."""
    from model.methods.registry import method_spec, parse_method_name

    return [m for m in baseline_methods() if scale in method_spec(parse_method_name(m)[0]).scales]


def planned_methods(params: EvaluateParams) -> list[str]:
    """Every method the job runs at one scale or another: a benchmark's defaults and include_learned merged."""
    if not isinstance(params, BenchmarkParams):
        return list(params.methods)
    methods = baseline_methods(params.methods, params.all_presets)
    return list(dict.fromkeys(methods + list(params.include_learned or [])))


def runs_at(method: str, scale: int, storage: Storage) -> bool:
    """Whether ``method`` runs at ``scale`` (other problems with it raise their domain error)."""
    try:
        check_method(method, scale, storage)
    except Invalid as error:
        if error.code != "unsupported_scale":
            raise
        return False
    return True


def check(params: EvaluateParams, storage: Storage, settings: Settings | None = None) -> dict[str, Any]:
    dataset = open_dataset(storage, params.dataset)
    scales = benchmark_scales(params.scale)
    for scale in scales:
        split_sequences(dataset, params.dataset, params.split, scale)
    benchmark = isinstance(params, BenchmarkParams)
    if benchmark:
        for text in params.include_learned or []:
            if not (is_model_ref(text) or looks_like_path(text) or _is_pretrained(text)):
                raise Invalid("invalid_request", f"include_learned: {text!r} is not a trained model; give a "
                         "model reference (models:/NAME@ALIAS), a pretrained model or a checkpoint file")
    try:
        methods = planned_methods(params)
    except (KeyError, ValueError) as error:
        raise Invalid("unknown_method", str(error.args[0] if error.args else error)) from None
    if benchmark and params.methods is None:  # defaults: only those that run at a requested scale
        methods = [m for m in methods if m in (params.include_learned or [])
                   or any(runs_at(m, scale, storage) for scale in scales)]
    for method in methods:
        if len(scales) == 1:
            check_method(method, scales[0], storage)
        elif not any(runs_at(method, scale, storage) for scale in scales):
            check_method(method, scales[0], storage)  # raises: it runs at none of them
        if benchmark:
            _refuse_untrained(method)
    checked = {**params.model_dump(), "methods": methods}
    if benchmark:
        checked["include_learned"] = None  # merged into methods above
        checked["all_presets"] = False  # applied above
    return checked


def _is_pretrained(text: str) -> bool:
    from model.deployment.pretrained import is_pretrained

    return is_pretrained(text)


def _refuse_untrained(text: str) -> None:
    """A benchmark runs learned methods only from trained weights: a registry name of one would be untrained."""
    from model.deployment.pretrained import is_pretrained
    from model.methods.registry import method_spec, parse_method_name

    if is_model_ref(text) or looks_like_path(text) or is_pretrained(text):
        return
    name = parse_method_name(text)[0]
    if method_spec(name).learned:
        raise Invalid("untrained_method", f"method {text!r} is learned and a registry preset has no trained "
                 f"weights; benchmark a model reference (models:/NAME@ALIAS) or a checkpoint instead")
