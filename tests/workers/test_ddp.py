"""DDP launching: 2 gloo ranks match 1 process on the same global batch; stop ends every rank; failures are reported."""

from __future__ import annotations

import os
import socket

import pytest
import torch

from model.training.checkpoint import load_checkpoint
from model.training.train import TrainConfig, prepare, train
from tests.builders import write_tiny_dataset
from tests.model.training_fixtures import TINY_METHOD
from workers.ddp import RankError, TrainingJob, free_port, launch

FIXTURES = "tests.model.training_fixtures"  # registers the tiny method inside the rank processes


class Stop(Exception):
    pass


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("ddp") / "data")


def tiny_config(data, out, **changes) -> TrainConfig:
    values = dict(method=TINY_METHOD, data=str(data), crop=8, frames_per_sample=3, batch=4, steps=3,
                  lr=0.01, warmup_steps=0, out=str(out), checkpoint_every=0, validate_every=0, device="cpu")
    values.update(changes)
    return TrainConfig(**values)


def test_two_gloo_ranks_give_the_weights_of_one_process(data, tmp_path):
    single = train(tiny_config(data, tmp_path / "one"))
    reports = []
    double = launch(tiny_config(data, tmp_path / "two", world_size=2), track=False, imports=[FIXTURES],
                    progress=lambda *report: reports.append(report))

    assert [r[:2] for r in reports] == [(1, 3), (2, 3), (3, 3)]
    assert double["steps"] == 3 and double["rank"] == 0
    # The logged loss is the global batch's, the same as one process computes.
    assert double["losses"]["loss"] == pytest.approx(single["losses"]["loss"], rel=1e-5)
    one, two = load_checkpoint(single["checkpoint"]), load_checkpoint(double["checkpoint"])
    assert len(two["rng"]) == 2  # every rank's RNG, for resuming
    difference = 0.0
    for name, tensor in one["model"].items():
        torch.testing.assert_close(two["model"][name], tensor, rtol=1e-5, atol=1e-6)
        difference = max(difference, float((tensor - two["model"][name]).abs().max()))
    # The comparison means something only if training moved the weights far more than the ranks disagree.
    _, _, untrained = prepare(tiny_config(data, tmp_path / "one"))
    change = max(float((one["model"][name] - value).abs().max()) for name, value in untrained.state_dict().items())
    assert change > 1e-2 > 1e3 * difference


def test_stop_ends_the_launcher_and_every_rank(data, tmp_path):
    job = TrainingJob(tiny_config(data, tmp_path / "stopped", world_size=2, steps=100_000), track=False,
                      imports=[FIXTURES])
    job.start()

    def stop_when_training(step, total, message):
        raise Stop

    try:
        with pytest.raises(Stop):
            job.wait(stop_when_training)  # returns control once rank 0 reports its first step
        assert job.running
    finally:
        job.stop(grace=5)
    assert not job.running and job.process.returncode != 0
    with pytest.raises(ProcessLookupError):
        os.killpg(job.process.pid, 0)  # nobody is left in the job's process group


def test_a_failing_rank_is_reported_with_its_error(data, tmp_path):
    # Without the fixtures import the ranks' registry has no tiny method.
    with pytest.raises(RankError, match="unknown method 'tiny_test'"):
        launch(tiny_config(data, tmp_path / "failing"), track=False)


def test_free_port_is_bindable():
    port = free_port()
    assert 1024 <= port < 65536
    with socket.socket() as server:
        server.bind(("127.0.0.1", port))


def test_config_is_checked_before_anything_starts(data, tmp_path):
    with pytest.raises(ValueError, match="does not split evenly"):
        TrainingJob(tiny_config(data, tmp_path, world_size=3))


@pytest.mark.slow
def test_torchrun_ranks_train_like_the_launcher(data, tmp_path):
    """Multi-node training runs each rank under torchrun (`python -m workers.ddp --torchrun`); one node, 2 ranks."""
    import json
    import subprocess
    import sys

    single = train(tiny_config(data, tmp_path / "one"))
    config = tiny_config(data, tmp_path / "torchrun", world_size=2)
    config_file = tmp_path / "train.json"
    config_file.write_text(json.dumps(config.to_dict()))
    command = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc-per-node", "2",
               "--rdzv-backend", "c10d", "--rdzv-endpoint", f"127.0.0.1:{free_port()}",
               "-m", "workers.ddp", "--torchrun", "--config", str(config_file), "--import", FIXTURES]
    finished = subprocess.run(command, capture_output=True, text=True, timeout=300,
                              env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert finished.returncode == 0, finished.stderr[-3000:]
    one, two = load_checkpoint(single["checkpoint"]), load_checkpoint(tmp_path / "torchrun" / "last.pt")
    assert two["step"] == 3
    for name, tensor in one["model"].items():
        torch.testing.assert_close(two["model"][name], tensor, rtol=1e-5, atol=1e-6)
