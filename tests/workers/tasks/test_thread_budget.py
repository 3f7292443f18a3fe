"""A job's torch thread budget (DENOISER_JOB_THREADS): set in the worker, shared among DDP ranks."""

from __future__ import annotations

import torch

from core.jobs.kinds import JOB_PARAMS
from workers.tasks.jobs import apply_job_threads
from core.jobs.train import rank_threads, train_config


def test_the_job_budget_is_set_in_the_worker(settings):
    before = torch.get_num_threads()
    try:
        apply_job_threads(settings.model_copy(update={"job_threads": 1}))
        assert torch.get_num_threads() == 1
        apply_job_threads(settings)  # unset: left as it is
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_ranks_share_the_budget_and_a_jobs_own_threads_win(settings, storage, tmp_path):
    budget = settings.model_copy(update={"job_threads": 4})
    assert rank_threads(budget, 2) == 2 and rank_threads(budget, 8) == 1 and rank_threads(settings, 2) is None
    params = JOB_PARAMS["train"].model_validate({"dataset": "d", "method": "wskpn:xs", "world_size": 2})
    assert train_config(params, storage, budget, tmp_path, "cpu").threads == 2
    own = JOB_PARAMS["train"].model_validate({"dataset": "d", "method": "wskpn:xs", "world_size": 2, "threads": 3})
    assert train_config(own, storage, budget, tmp_path, "cpu").threads == 3
