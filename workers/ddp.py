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
Ranks started by torchrun (``--torchrun``, one node of a multi-node job: ``workers.elastic``) speak the same
protocol on torchrun's stdout, and die with their torchrun.
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
from collections.abc import Callable, Sequence
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

    # Whether this launch's ranks include rank 0 for sure (one node of several may not have it).
    reports_result = True

    def start(self) -> None:
        if self.process is not None:
            raise RuntimeError("this job was already started")
        environment = self.environment()
        # The ranks import this project (and ``imports``) by name wherever the parent was started from.
        environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPOSITORY_ROOT),
                                                                  environment.get("PYTHONPATH")]))
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.log_path, "wb") as log:
            # process_group=0 would do too; a new session also detaches the job from the terminal's Ctrl-C,
            # which the parent turns into stop().
            self.process = subprocess.Popen(self.command(), stdout=subprocess.PIPE, stderr=log, env=environment,
                                            start_new_session=True, preexec_fn=self.preexec)
        self._reader = threading.Thread(target=self._read_messages, name="ddp-messages", daemon=True)
        self._reader.start()

    preexec = None  # run in the launcher's process before it starts (workers.elastic: die with the worker)

    def environment(self) -> dict[str, str]:
        self.port = free_port()
        return dict(os.environ, MASTER_ADDR="127.0.0.1", MASTER_PORT=str(self.port))

    def command(self) -> list[str]:
        return [sys.executable, "-m", "workers.ddp", *self.rank_arguments()]

    def rank_arguments(self) -> list[str]:
        """What every rank is told (``launcher_main``'s options)."""
        arguments = ["--config-json", json.dumps(self.config.to_dict())]
        arguments += ["--track"] if self.track else []
        for module in self.imports:
            arguments += ["--import", module]
        return arguments

    def _read_messages(self) -> None:
        for line in self.process.stdout:
            text = line.decode("utf-8", errors="replace")
            if text.startswith(MESSAGE_PREFIX):
                self._messages.put(json.loads(text[len(MESSAGE_PREFIX):]))
        self._messages.put(None)  # end of stream: the launcher (and so every rank) is done

    def wait(self, progress: Progress | None = None) -> dict[str, Any] | None:
        """Relay rank 0's progress until the job ends; return rank 0's result (None: rank 0 ran elsewhere and
        ``reports_result`` is false) or raise RankError."""
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
        if code != 0 or (result is None and self.reports_result):
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
    parser.add_argument("--run-id", default=None, help="MLflow run rank 0 continues when no checkpoint names one "
                        "(a multi-node job creates its run before its nodes start)")
    parser.add_argument("--collective-timeout", type=float, default=None, metavar="SECONDS",
                        help="how long a rank waits in one collective before it fails (torch's default: none given)")
    parser.add_argument("--import", dest="imports", action="append", default=[], metavar="MODULE",
                        help="module every rank imports first (methods registered outside the registry)")
    args = parser.parse_args(argv)
    if (args.config_json is None) == (args.config is None):
        parser.error("give exactly one of --config-json and --config")
    text = args.config_json if args.config_json is not None else args.config.read_text()
    config = TrainConfig.from_dict(json.loads(text))
    options = {"run_id": args.run_id, "collective_timeout": args.collective_timeout}
    if args.torchrun:
        return _torchrun_rank(config, args.track, args.imports, options)
    if config.world_size == 1:
        _rank_main(0, config.to_dict(), args.track, args.imports, options)
        return 0
    import torch.multiprocessing

    torch.multiprocessing.start_processes(_rank_main, args=(config.to_dict(), args.track, args.imports, options),
                                          nprocs=config.world_size, join=True, start_method="spawn")
    return 0


def _torchrun_rank(config: TrainConfig, track: bool, imports: list[str], options: dict[str, Any]) -> int:
    """One rank started by torchrun (one node of a multi-node job): torchrun set MASTER_ADDR/PORT, RANK, WORLD_SIZE
    and LOCAL_WORLD_SIZE; the rank dies with its torchrun, which may be killed with its worker."""
    import torch

    _die_with_parent()
    rank, world_size = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
    if world_size != config.world_size:
        raise SystemExit(f"torchrun started {world_size} ranks, the config asks for world_size {config.world_size}")
    if config.device != "cpu" and torch.cuda.is_available():
        # One GPU per local rank: device indices count within a node, ranks across nodes.
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    local_ranks = int(os.environ.get("LOCAL_WORLD_SIZE", world_size))
    _rank_main(rank, config.to_dict(), track, imports, {**options, "local_ranks": local_ranks})
    return 0


def parent_death_signal() -> Callable[[], None] | None:
    """A function that has the process calling it SIGKILLed when its parent dies (Linux's PR_SET_PDEATHSIG; None
    elsewhere). Built before a fork, so a ``preexec_fn`` only calls into libc."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl
    return lambda: prctl(1, signal.SIGKILL)  # 1: PR_SET_PDEATHSIG


def _die_with_parent() -> None:
    """torchrun starts ranks in sessions of their own, so a torchrun killed with its worker would otherwise leave
    them training, holding their peers' collectives."""
    arm = parent_death_signal()
    if arm is None:
        return
    arm()
    if os.getppid() == 1:  # the parent died before the call above: nobody would be signalled
        os.kill(os.getpid(), signal.SIGKILL)


class _RunOfJob:
    """Rank 0's tracker when the job created its MLflow run before the ranks started: ``start`` continues that
    run unless a checkpoint names one (the same run, once the job has checkpointed)."""

    def __init__(self, inner: Any, job_run_id: str) -> None:
        self._inner = inner
        self._job_run_id = job_run_id

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def start(self, params: dict[str, Any], resume_run_id: str | None = None) -> None:
        self._inner.start(params, resume_run_id or self._job_run_id)


def _rank_main(rank: int, config_values: dict[str, Any], track: bool, imports: list[str],
               options: dict[str, Any] | None = None) -> None:
    import importlib

    import torch

    from model.training.train import train

    options = options or {}
    # Only rank 0 speaks the protocol on stdout; anything else printed, by any rank, goes to the log.
    messages = os.fdopen(os.dup(1), "w", buffering=1) if rank == 0 else None
    os.dup2(2, 1)
    for module in imports:
        importlib.import_module(module)
    config = TrainConfig.from_dict(config_values)
    if config.threads is None and config.device != "cuda":
        # Ranks on one CPU share its cores; torch would otherwise give every rank all of them.
        local_ranks = options.get("local_ranks") or config.world_size
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // local_ranks))
    tracker = None
    if track and rank == 0:
        from core.tracking import MLflowTracker

        tracker = MLflowTracker(config.tracking_uri, config.experiment)
        if options.get("run_id"):
            tracker = _RunOfJob(tracker, options["run_id"])

    def send(message: dict[str, Any]) -> None:
        messages.write(MESSAGE_PREFIX + json.dumps(message, default=str) + "\n")

    progress = (lambda current, total, text: send({"progress": [current, total, text]})) if rank == 0 else None
    result = train(config, tracker=tracker, rank=rank, world_size=config.world_size, progress=progress,
                   collective_timeout=options.get("collective_timeout"))
    if rank == 0:
        send({"result": result})
        messages.close()


if __name__ == "__main__":
    # Run through the module's own import, so the rank function pickles as workers.ddp._rank_main.
    from workers.ddp import launcher_main as _launcher_main

    sys.exit(_launcher_main(sys.argv[1:]))
