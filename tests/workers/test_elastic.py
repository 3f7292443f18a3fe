"""One node's torchrun command: the rendezvous, the node count, the restarts and the timeouts come from the job and
the settings; the address other nodes reach."""

from __future__ import annotations

import socket

import pytest

from core.settings import Settings
from model.training.train import TrainConfig
from tests.model.training_fixtures import TINY_METHOD
from workers.elastic import ElasticNode, advertised_host


def node(tmp_path, number: int, **settings) -> ElasticNode:
    config = TrainConfig(method=TINY_METHOD, data=str(tmp_path), out=str(tmp_path / "out"), world_size=4, batch=4,
                         device="cpu")
    return ElasticNode(config, job_id="job1", node=number, nodes=2, endpoint="10.0.0.5:29400", local_addr="10.0.0.6",
                       settings=Settings(data_dir=tmp_path, **settings), run_id="run1")


def test_each_node_runs_torchrun_with_the_jobs_rendezvous_and_the_settings_timeouts(tmp_path):
    command = node(tmp_path, 1, rendezvous_timeout_seconds=42, collective_timeout_seconds=99,
                   node_max_restarts=5).command()
    launcher = command[command.index("torch.distributed.run") + 1:command.index("workers.ddp") - 1]
    assert launcher == ["--nnodes=2", "--nproc-per-node=2", "--rdzv-backend=c10d", "--rdzv-endpoint=10.0.0.5:29400",
                        "--rdzv-id=job1", "--rdzv-conf=is_host=0,join_timeout=42,read_timeout=42",
                        "--max-restarts=5", "--local-addr=10.0.0.6", "--monitor-interval=1"]
    ranks = command[command.index("workers.ddp") + 1:]
    assert ranks[0] == "--torchrun" and "--collective-timeout=99" in ranks and ranks[-2:] == ["--run-id", "run1"]
    assert "is_host=1" in " ".join(node(tmp_path, 0).command())  # only the first node hosts the rendezvous
    assert node(tmp_path, 0).environment()["TORCH_DISABLE_SHARE_RDZV_TCP_STORE"] == "1"


def test_ranks_must_split_evenly_over_the_nodes(tmp_path):
    config = TrainConfig(method=TINY_METHOD, data=str(tmp_path), world_size=3, batch=3, device="cpu")
    with pytest.raises(ValueError, match="does not split evenly over 2 nodes"):
        ElasticNode(config, job_id="j", node=0, nodes=2, endpoint="h:1", local_addr="h", settings=Settings())


def test_the_advertised_host_is_the_setting_else_the_hostnames_address(monkeypatch, tmp_path):
    assert advertised_host(Settings(data_dir=tmp_path, node_host="node-a.example")) == "node-a.example"
    monkeypatch.setattr(socket, "gethostbyname", lambda name: "10.1.2.3")
    assert advertised_host(Settings(data_dir=tmp_path)) == "10.1.2.3"
    monkeypatch.setattr(socket, "gethostbyname", lambda name: "127.0.1.1")
    monkeypatch.setattr(socket, "socket", _Route)
    assert advertised_host(Settings(data_dir=tmp_path)) == "10.9.8.7"  # the default route's, not loopback


class _Route:
    """A UDP socket whose connect picks the route of address 10.9.8.7."""

    def __init__(self, *args) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        pass

    def connect(self, address) -> None:
        pass

    def getsockname(self):
        return ("10.9.8.7", 40000)
