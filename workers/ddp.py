"""Launching the ranks of a DistributedDataParallel training job, and stopping them.

Celery's prefork children are daemonic and may not start child processes, and a job must be cancellable as
a whole. So a job runs in a *launcher* subprocess (``python -m workers.ddp``) started in a session and process
group of its own; the launcher starts the ``world_size`` rank processes with
``torch.multiprocessing.start_processes`` (spawn: fresh interpreters, no forked threads), which stay in its
group. ``TrainingJob.stop`` signals the whole group, ranks included, even if the launcher is already gone.

Rendezvous: MASTER_ADDR=127.0.0.1 and a free port per job (the OS picks one when a socket binds port 0; it is
released just before the ranks bind it, a race only with processes that grab arbitrary ports meanwhile).

Rank 0 reports to the parent through the launcher's stdout, one JSON message a line (``{"progress": [current,
total, message]}``, then ``{"result": {...}}``); everything else any rank prints goes to the job's log file
(``<out>/ddp.log``), whose tail is quoted when a rank fails. Only rank 0 tracks (MLflow) and checkpoints.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from model.training.train import Progress, TrainConfig
from core.jobs.files import DDP_LOG_FILE

MESSAGE_PREFIX = "denoiser-ddp "  # marks protocol lines on the launcher's stdout
REPOSITORY_ROOT = Path(__file__).resolve().parents[1]


class RankError(RuntimeError):
    """A rank (or the launcher) exited with an error; the message quotes the end of the job's log."""


def free_port(host: str = "127.0.0.1") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


class TrainingJob:
    """One training job's ranks, launched from this (non-daemon) process; ``start``, then ``wait`` or ``stop``.

    ``track``: rank 0 logs to MLflow (``core.tracking.MLflowTracker`` at ``config.tracking_uri``).
    ``imports``: modules each rank imports before building the method, for methods registered outside
    ``model.methods.registry.METHOD_MODULES`` (plugins, tests).
    """

    def __init__(self, config: TrainConfig, *, track: bool = True, imports: Sequence[str] = ()) -> None:
        config.check()
        self.config = config
        self.track = track
        self.imports = tuple(imports)
        self.log_path = Path(config.out) / DDP_LOG_FILE
        self.port: int | None = None
        self.process: subprocess.Popen | None = None
        self._messages: queue.Queue = queue.Queue()
        self._reader: threading.Thread | None = None

    def start(self) -> None:
        if self.process is not None:
            raise RuntimeError("this job was already started")
        self.port = free_port()
        environment = dict(os.environ, MASTER_ADDR="127.0.0.1", MASTER_PORT=str(self.port))
        # The ranks import this project (and ``imports``) by name wherever the parent was started from.
        environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPOSITORY_ROOT),
                                                                  environment.get("PYTHONPATH")]))
        command = [sys.executable, "-m", "workers.ddp", "--config-json", json.dumps(self.config.to_dict())]
        command += ["--track"] if self.track else []
        for module in self.imports:
            command += ["--import", module]
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "wb") as log:
            # process_group=0 would do too; a new session also detaches the job from the terminal's Ctrl-C,
            # which the parent turns into stop().
            self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=log, env=environment,
                                            start_new_session=True)
        self._reader = threading.Thread(target=self._read_messages, name="ddp-messages", daemon=True)
        self._reader.start()

    def _read_messages(self) -> None:
        for line in self.process.stdout:
            text = line.decode("utf-8", errors="replace")
            if text.startswith(MESSAGE_PREFIX):
                self._messages.put(json.loads(text[len(MESSAGE_PREFIX):]))
        self._messages.put(None)  # end of stream: the launcher (and so every rank) is done

    def wait(self, progress: Progress | None = None) -> dict[str, Any]:
        """Relay rank 0's progress until the job ends; return rank 0's result or raise RankError."""
        if self.process is None:
            raise RuntimeError("start the job before waiting for it")
        result = None
        while True:
            message = self._messages.get()
            if message is None:
                break
            if "progress" in message and progress is not None:
                progress(*message["progress"])
            if "result" in message:
                result = message["result"]
        code = self.process.wait()
        if code != 0 or result is None:
            raise RankError(f"training job failed (launcher exit status {code}); end of {self.log_path}:\n"
                            f"{self.log_tail()}")
        return result

    def log_tail(self, lines: int = 30) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def stop(self, grace: float = 10.0) -> None:
        """Terminate the launcher and every rank (SIGTERM, then SIGKILL after ``grace`` seconds)."""
        if self.process is None:
            return
        group = self.process.pid  # the session leader's pid is the group id
        if _signal_group(group, signal.SIGTERM):
            deadline = time.monotonic() + grace
            # poll() reaps the launcher: a zombie would still count as a member of the group.
            while (self.process.poll() is None or _signal_group(group, 0)) and time.monotonic() < deadline:
                time.sleep(0.05)
            _signal_group(group, signal.SIGKILL)
        self.process.wait()
        # Every writer of the message pipe is gone now, so the reader sees its end and the pipe can be closed.
        self._reader.join(timeout=grace)
        if not self._reader.is_alive():
            self.process.stdout.close()


def _signal_group(group: int, sig: int) -> bool:
    """Send ``sig`` to a process group (0: only check it exists); False when the group has no process left."""
    try:
        os.killpg(group, sig)
    except ProcessLookupError:
        return False
    return True


def launch(config: TrainConfig, *, track: bool = True, imports: Sequence[str] = (),
           progress: Progress | None = None) -> dict[str, Any]:
    """Run a training job to its end in ``config.world_size`` rank processes; returns rank 0's result.

    Interrupted (KeyboardInterrupt, or any exception in ``progress``), the whole job is stopped first.
    """
    job = TrainingJob(config, track=track, imports=imports)
    job.start()
    try:
        return job.wait(progress)
    finally:
        job.stop()


# ------------------------------------------------------------------------- inside the launcher

def launcher_main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m workers.ddp", description="Run the ranks of a training job "
                                     "(started by workers.ddp.TrainingJob; MASTER_ADDR/MASTER_PORT must be set).")
    parser.add_argument("--config-json", default=None, help="TrainConfig as JSON")
    parser.add_argument("--config", type=Path, default=None, metavar="FILE.json",
                        help="TrainConfig as a JSON file (instead of --config-json)")
    parser.add_argument("--torchrun", action="store_true",
                        help="this process is one rank started by torchrun (RANK, WORLD_SIZE, LOCAL_RANK and the "
                             "rendezvous come from its environment): multi-node training")
    parser.add_argument("--track", action="store_true", help="rank 0 logs to MLflow")
    parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE",
                        help="module every rank imports first (methods registered outside the registry)")
    args = parser.parse_args(argv)
    if (args.config_json is None) == (args.config is None):
        parser.error("give exactly one of --config-json and --config")
    text = args.config_json if args.config_json is not None else args.config.read_text()
    config = TrainConfig.from_dict(json.loads(text))
    if args.torchrun:
        return _torchrun_rank(config, args.track, args.imports)
    if config.world_size == 1:
        _rank_main(0, config.to_dict(), args.track, args.imports)
        return 0
    import torch.multiprocessing

    torch.multiprocessing.start_processes(_rank_main, args=(config.to_dict(), args.track, args.imports),
                                          nprocs=config.world_size, join=True, start_method="spawn")
    return 0


def _torchrun_rank(config: TrainConfig, track: bool, imports: list[str]) -> int:
    """One rank of a multi-node job started by torchrun: torchrun set MASTER_ADDR/PORT, RANK and WORLD_SIZE."""
    import importlib

    import torch

    from model.training.train import train

    rank, world_size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    if world_size != config.world_size:
        raise SystemExit(f"torchrun started {world_size} ranks, the config asks for world_size {config.world_size}")
    for module in imports:
        importlib.import_module(module)
    if config.device != "cpu" and torch.cuda.is_available():
        # One GPU per local rank: device indices count within a node, ranks across nodes.
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    tracker = None
    if track and rank == 0:
        from core.tracking import MLflowTracker

        tracker = MLflowTracker(config.tracking_uri, config.experiment)
    result = train(config, tracker=tracker, rank=rank, world_size=world_size)
    if rank == 0:
        print(json.dumps({"result": result}, default=str))
    return 0


def _rank_main(rank: int, config_values: dict[str, Any], track: bool, imports: list[str]) -> None:
    import importlib

    import torch

    from model.training.train import train

    # Only rank 0 speaks the protocol on stdout; anything else printed, by any rank, goes to the log.
    messages = os.fdopen(os.dup(1), "w", buffering=1) if rank == 0 else None
    os.dup2(2, 1)
    for module in imports:
        importlib.import_module(module)
    config = TrainConfig.from_dict(config_values)
    if config.threads is None and config.device != "cuda":
        # Ranks on one CPU share its cores; torch would otherwise give every rank all of them.
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // config.world_size))
    tracker = None
    if track and rank == 0:
        from core.tracking import MLflowTracker

        tracker = MLflowTracker(config.tracking_uri, config.experiment)

    def send(message: dict[str, Any]) -> None:
        messages.write(MESSAGE_PREFIX + json.dumps(message) + "\n")

    progress = (lambda current, total, text: send({"progress": [current, total, text]})) if rank == 0 else None
    result = train(config, tracker=tracker, rank=rank, world_size=config.world_size, progress=progress)
    if rank == 0:
        send({"result": result})
        messages.close()


if __name__ == "__main__":
    # Run through the module's own import, so the rank function pickles as workers.ddp._rank_main.
    from workers.ddp import launcher_main as _launcher_main

    sys.exit(_launcher_main(sys.argv[1:]))
