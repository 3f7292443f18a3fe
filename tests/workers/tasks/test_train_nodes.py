"""Multi-node training jobs in this process: node 0 is ``execute`` (the job's execution), the other nodes' tasks run
in threads (``workers.tasks.nodes.run_node``), each node a real torchrun with gloo ranks on 127.0.0.1."""

from __future__ import annotations

import os
import threading

import pytest
import torch

from core.errors import Invalid
from core.jobs.kinds import JOB_PARAMS, check
from model.training.checkpoint import load_checkpoint
from model.training.train import TrainConfig, train
from tests.model.training_fixtures import TINY_METHOD
from tests.workers.tasks.datasets import store_dataset
from workers.elastic import ElasticNode
from workers.tasks import nodes as nodes_module
from workers.tasks.jobs import execute
from workers.tasks.rendezvous import NodeBoard

TIMEOUTS = {"node_host": "127.0.0.1", "rendezvous_timeout_seconds": 60, "collective_timeout_seconds": 60}


@pytest.fixture
def node_settings(settings):
    return settings.model_copy(update=TIMEOUTS)


def train_params(**changes) -> dict:
    return {"dataset": "tiny", "method": TINY_METHOD, "steps": 3, "crop": 8, "batch": 4, "frames_per_sample": 3,
            "lr": 0.01, "warmup_steps": 0, "validate_every": 0, "checkpoint_every": 1, "track": False, **changes}


class ThreadNodes:
    """Runs the node tasks node 0 sends in threads of this process, as workers of its queue would."""

    def __init__(self, store, storage, settings) -> None:
        self.store, self.storage, self.settings = store, storage, settings
        self.threads: list[threading.Thread] = []
        self.results: list[dict] = []

    def sender(self, queue: str):
        def send(job_id: str, node: int, attempt: int) -> None:
            thread = threading.Thread(target=lambda: self.results.append(nodes_module.run_node(
                job_id, node, attempt, self.store, self.storage, self.settings)), daemon=True)
            thread.start()
            self.threads.append(thread)

        return send

    def join(self) -> None:
        for thread in self.threads:
            thread.join(timeout=60)
            assert not thread.is_alive()


def test_two_nodes_train_the_weights_of_one_process_with_the_same_global_batch(store, storage, node_settings,
                                                                               monkeypatch, tmp_path):
    store_dataset(storage)
    others = ThreadNodes(store, storage, node_settings)
    monkeypatch.setattr(nodes_module, "celery_node_sender", others.sender)
    params = check("train", JOB_PARAMS["train"].model_validate(train_params(nodes=2)), storage, node_settings)
    assert params["nodes"] == 2 and params["world_size"] == 2  # one rank per node unless told otherwise
    job_id = store.create("train", params, "cpu", "cpu")["id"]

    execute(job_id, store, storage, node_settings)
    others.join()

    record = store.require(job_id)
    assert record["state"] == "succeeded", record["error"]
    assert record["result"]["steps"] == 3 and record["progress"]["current"] == 3
    assert [r["state"] for r in others.results] == ["done"]
    assert NodeBoard(store, job_id, 60).rendezvous() is None  # cleared once the job ended
    folder = storage.job(job_id) / "checkpoints"
    assert (folder / "ddp-node0.log").is_file() and (folder / "ddp-node1.log").is_file()
    # One process with the same global batch (4: 2 per rank on 2 nodes). The ranks' gradients are averaged by an
    # allreduce, whose float sums round differently from one process's batch mean: equal to float32 rounding.
    single = train(TrainConfig(**{**{k: v for k, v in train_params().items() if k not in ("dataset", "track")},
                                  "data": str(storage.dataset("tiny")), "out": str(tmp_path / "one"),
                                  "device": "cpu"}))
    one, two = load_checkpoint(single["checkpoint"]), load_checkpoint(folder / "last.pt")
    assert two["step"] == 3 and len(two["rng"]) == 2
    for name, tensor in one["model"].items():
        torch.testing.assert_close(two["model"][name], tensor, rtol=1e-5, atol=1e-6)
    assert max(float((tensor - two["model"][name]).abs().max()) for name, tensor in one["model"].items()) < 1e-5


def test_nodes_are_checked_against_the_services_maximum_and_the_ranks(storage, node_settings):
    store_dataset(storage)
    with pytest.raises(Invalid, match="DENOISER_MAX_TRAIN_NODES=2"):
        check("train", JOB_PARAMS["train"].model_validate(train_params(nodes=3, batch=3)), storage,
              node_settings.model_copy(update={"max_train_nodes": 2}))
    with pytest.raises(ValueError, match="does not split evenly over 2 nodes"):
        JOB_PARAMS["train"].model_validate(train_params(nodes=2, world_size=3, batch=6))
    with pytest.raises(ValueError, match="greater than or equal to 1"):
        JOB_PARAMS["train"].model_validate(train_params(nodes=0))
    params = JOB_PARAMS["train"].model_validate(train_params(nodes=2, world_size=4))
    assert (params.nodes, params.world_size) == (2, 4)


def _no_process_left(pid: int) -> bool:
    try:
        os.killpg(pid, 0)
    except ProcessLookupError:
        return True
    return False


@pytest.mark.slow
def test_a_cancel_stops_every_node(store, storage, node_settings, monkeypatch):
    store_dataset(storage)
    others = ThreadNodes(store, storage, node_settings)
    monkeypatch.setattr(nodes_module, "celery_node_sender", others.sender)
    job_id = store.create("train", check("train", JOB_PARAMS["train"].model_validate(train_params(
        nodes=2, steps=1_000_000, checkpoint_every=0)), storage, node_settings), "cpu", "cpu")["id"]
    launched = []
    monkeypatch.setattr(ElasticNode, "start", _recording(ElasticNode.start, launched))

    def cancel_once_training(report: dict) -> None:
        if report["current"] > 0 and not store.cancel_requested(job_id):
            store.request_cancel(job_id)

    execute(job_id, store, storage, node_settings, sink=cancel_once_training)
    others.join()

    assert store.require(job_id)["state"] == "cancelled"
    assert [r["state"] for r in others.results] == ["stopped"]
    assert len(launched) == 2 and all(_no_process_left(node.process.pid) for node in launched)


def _recording(start, launched: list):
    def recorded(node) -> None:
        launched.append(node)
        start(node)

    return recorded


def test_a_node_no_worker_takes_fails_the_job_after_the_rendezvous_timeout(store, storage, node_settings,
                                                                           monkeypatch):
    store_dataset(storage)
    monkeypatch.setattr(nodes_module, "celery_node_sender", lambda queue: lambda job_id, node, attempt: None)
    settings = node_settings.model_copy(update={"rendezvous_timeout_seconds": 3})
    job_id = store.create("train", check("train", JOB_PARAMS["train"].model_validate(train_params(nodes=2)),
                                         storage, settings), "cpu", "cpu")["id"]

    execute(job_id, store, storage, settings)

    record = store.require(job_id)
    assert record["state"] == "failed" and record["error"]["code"] == "nodes_missing", record["error"]
    assert "node(s) 1 of 2 never started" in record["error"]["message"]


def test_a_node_task_of_another_attempt_or_of_an_ended_job_returns_at_once(store, storage, node_settings):
    store_dataset(storage)
    job_id = store.create("train", check("train", JOB_PARAMS["train"].model_validate(train_params(nodes=2)),
                                         storage, node_settings), "cpu", "cpu")["id"]
    board = NodeBoard(store, job_id, 60)
    assert nodes_module.run_node(job_id, 1, 1, store, storage, node_settings)["skipped"] == "another attempt"
    board.publish(2, "127.0.0.1:1", 2)  # node 0 of attempt 2 runs the job now
    assert nodes_module.run_node(job_id, 1, 1, store, storage, node_settings)["skipped"] == "another attempt"
    store.finish(job_id, "cancelled")
    assert nodes_module.run_node(job_id, 1, 2, store, storage, node_settings)["skipped"] == "finished"
    assert board.node(1) is None  # none of them started a torchrun


def test_node_zero_replaces_a_lost_node_at_most_node_max_restarts_times(store, storage, node_settings):
    from workers.tasks.context import JobContext

    record = store.create("train", train_params(nodes=2), "cpu", "cpu")
    settings = node_settings.model_copy(update={"node_max_restarts": 1})
    context = JobContext(record, store, storage, settings, "owner")
    board, sent = NodeBoard(store, record["id"], 60), []
    supervisor = nodes_module._Supervisor(board, context, 2, 1, lambda *task: sent.append(task))
    supervisor.tick()
    assert supervisor.never_started() == [1] and sent == []  # not started yet: the rendezvous timeout waits
    for _ in range(2):
        board.mark(1, 1, "running", "worker-b")
        supervisor.tick()
        assert supervisor.never_started() == []
        store.redis.delete(f"{store.key(record['id'])}:node:1")  # its key lapsed: the node died
        supervisor.tick()
    assert sent == [(record["id"], 1, 1)]  # one replacement, then no more
    board.mark(1, 1, "done", "worker-c")
    supervisor.tick()
    assert sent == [(record["id"], 1, 1)]  # a node that ended is not lost
