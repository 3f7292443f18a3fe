"""The ``stability`` job's check: the scenarios the dataset allows (from its manifests), and every method."""

from __future__ import annotations

from typing import Any

from core.errors import Invalid
from core.jobs.checks import invalid, open_dataset
from core.jobs.methods import check_method
from core.jobs.specs import StabilityParams
from core.settings import Settings
from core.storage import Storage


def scenario_names(params: StabilityParams) -> tuple[str, ...]:
    from model.names import STABILITY_SCENARIOS

    return tuple(dict.fromkeys(params.scenarios)) if params.scenarios else STABILITY_SCENARIOS


def check(params: StabilityParams, storage: Storage, settings: Settings | None = None) -> dict[str, Any]:
    from model.evaluation.stability import plan_scenarios

    dataset = open_dataset(storage, params.dataset)
    try:
        plan = plan_scenarios(dataset.root, params.scale, names=scenario_names(params), base=params.base)
    except ValueError as error:
        raise invalid(error, "invalid_scenarios") from None
    if not plan.names:
        raise Invalid("no_scenarios", f"none of the scenarios can be built from dataset {params.dataset!r}: "
                 + "; ".join(f"{m['name']}: {m['reason']}" for m in plan.missing))
    for method in params.methods:
        check_method(method, params.scale, storage)
    return {**params.model_dump(), "scenarios": list(scenario_names(params))}
