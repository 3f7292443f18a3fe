"""core.names: the one module of shared constants agrees with the library and the schemas that use it."""

from __future__ import annotations

import typing

from core import names
from core.jobs.kinds import JOB_PARAMS, KINDS
from core.jobs.specs import JobDevice, JobKind, JobState, JobSplit
from model.io.dataset import SPLITS
from model.names import STABILITY_SCENARIOS


def test_the_splits_are_the_libraries():
    assert names.SPLITS == SPLITS


def test_job_kinds_states_and_devices_are_the_schemas():
    # The client's plain names are the table's kinds, in its order.
    assert typing.get_args(JobKind) == names.JOB_KINDS == tuple(KINDS) == tuple(JOB_PARAMS)
    assert all(set(kind.devices) <= set(names.DEVICES) for kind in KINDS.values())
    assert typing.get_args(JobState) == names.JOB_STATES
    assert names.FINISHED_STATES < set(names.JOB_STATES)
    assert typing.get_args(JobDevice) == names.DEVICES == tuple(names.QUEUE_FOR_DEVICE)
    assert set(names.QUEUE_FOR_DEVICE.values()) <= set(names.QUEUES)
    assert typing.get_args(JobSplit) == SPLITS


def test_the_stability_scenarios_are_the_suites():
    from model.evaluation.stability import SCENARIOS

    assert STABILITY_SCENARIOS == SCENARIOS
