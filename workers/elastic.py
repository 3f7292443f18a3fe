"""One node of a multi-node training job: PyTorch's elastic launcher (torchrun) starting this node's ranks.

Every node of a job runs ``python -m torch.distributed.run`` with the same c10d rendezvous (the job id as the
rendezvous id, the endpoint its first node published: ``workers.tasks.rendezvous``), a fixed node count
(``--nnodes N``: min = max, so the global batch and the data each rank sees never change) and
``--max-restarts K``. Only the first node hosts the rendezvous store (``is_host``), so which process serves it
never depends on hostnames (every node of a one-machine test is 127.0.0.1). The ranks are ``python -m workers.ddp
--torchrun``: the protocol, tracking and checkpointing of ``workers.ddp``, unchanged.

The launch is a ``workers.ddp.TrainingJob`` (its own session and process group, stdout read for rank 0's
messages, ``stop`` signals the group; torchrun passes a SIGTERM on to its ranks), with one difference: torchrun
is SIGKILLed when the worker process that started it dies, and its ranks die with it (``workers.ddp``), so a
killed worker takes its node's ranks along instead of leaving them in their peers' collectives.
"""

from __future__ import annotations

import os
import socket
import sys
from collections.abc import Sequence
from pathlib import Path

from model.training.train import TrainConfig
from core.settings import Settings
from workers.ddp import TrainingJob, parent_death_signal


def advertised_host(settings: Settings) -> str:
    """The address other nodes reach this one at: DENOISER_NODE_HOST, else this machine's hostname's address, or
    when that is a loopback one (Debian maps the hostname to 127.0.1.1) the address of its default route."""
    if settings.node_host:
        return settings.node_host
    hostname = socket.gethostname()
    try:
        address = socket.gethostbyname(hostname)
    except OSError:
        return hostname
    if not address.startswith("127."):
        return address
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))  # a UDP connect only picks the route: nothing is sent
            return probe.getsockname()[0]
    except OSError:  # no route at all: one machine, where loopback is right
        return address


class ElasticNode(TrainingJob):
    """This node's torchrun: ``nodes`` x ``world_size / nodes`` ranks in all, rendezvous at ``endpoint``."""

    # Rank 0 lands on whichever node the rendezvous ranks first; a node without it has nothing to report.
    reports_result = False

    def __init__(self, config: TrainConfig, *, job_id: str, node: int, nodes: int, endpoint: str, local_addr: str,
                 settings: Settings, track: bool = True, run_id: str | None = None,
                 imports: Sequence[str] = ()) -> None:
        super().__init__(config, track=track, imports=imports)
        if config.world_size % nodes:
            raise ValueError(f"world_size {config.world_size} does not split evenly over {nodes} nodes")
        self.job_id = job_id
        self.node = node
        self.nodes = nodes
        self.endpoint = endpoint
        self.local_addr = local_addr
        self.settings = settings
        self.run_id = run_id
        self.log_path = Path(config.out) / f"ddp-node{node}.log"
        self.preexec = parent_death_signal()  # torchrun dies with the worker that started it

    def environment(self) -> dict[str, str]:
        # torchrun sets MASTER_ADDR/PORT, RANK and WORLD_SIZE for the ranks. Its default of sharing one TCP store
        # between agent and ranks caches the store's address from the first round: a survivor that is rank 0
        # again never publishes it for the next round, and a replacement node waits for it until the timeout.
        # Without sharing, every round's rank 0 publishes a fresh address.
        return dict(os.environ, TORCH_DISABLE_SHARE_RDZV_TCP_STORE="1")

    def command(self) -> list[str]:
        settings = self.settings
        timeout = settings.rendezvous_timeout_seconds
        # join_timeout: how long a round waits for all nodes (the start, and after a node was lost);
        # read_timeout: how long a store call waits (a node whose rendezvous host vanished fails after it).
        conf = f"is_host={int(self.node == 0)},join_timeout={timeout},read_timeout={timeout}"
        command = [sys.executable, "-m", "torch.distributed.run", f"--nnodes={self.nodes}",
                   f"--nproc-per-node={self.config.world_size // self.nodes}", "--rdzv-backend=c10d",
                   f"--rdzv-endpoint={self.endpoint}", f"--rdzv-id={self.job_id}", f"--rdzv-conf={conf}",
                   f"--max-restarts={settings.node_max_restarts}", f"--local-addr={self.local_addr}",
                   "--monitor-interval=1", "-m", "workers.ddp", "--torchrun", *self.rank_arguments(),
                   f"--collective-timeout={settings.collective_timeout_seconds}"]
        return command + (["--run-id", self.run_id] if self.run_id else [])

