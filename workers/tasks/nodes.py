"""Multi-node training jobs: the job's execution is node 0 and sends a node task for each other node.

A ``train`` job with ``nodes`` N > 1 runs as N executions of its queue's workers, each with one torchrun
(``workers.elastic.ElasticNode``) and ``world_size / N`` ranks:

- node 0 is the job's own execution (``run_job``: the lease, the record, the result). It picks a port, publishes
  ``host:port`` as this attempt's rendezvous (``workers.tasks.rendezvous``), creates or continues the job's
  MLflow run (the ranks' rank 0 continues it: one run, resumes included), starts its torchrun as the rendezvous
  host and sends ``run_train_node(job, n, attempt)`` for n = 1..N-1 to the queue it was delivered on;
- node n (``run_node``) reads the rendezvous and starts its torchrun there.

Every node relays rank 0's messages when rank 0 runs on it: progress to the job record, the result to Redis,
where node 0 collects it. Node tasks stop their torchrun when the job is cancelled or finished, or when another
attempt was published. A node whose state key lapses (killed) is replaced by node 0: its node task is sent again
(at most DENOISER_NODE_MAX_RESTARTS times) and the survivors' torchrun, whose ranks failed at their next
collective, restarts them in a new rendezvous round that the replacement joins; the ranks resume from the last
checkpoint. When node 0 dies, its lease lapses and recovery runs the job again: a new attempt, a new rendezvous.
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

from core.celery_app import app
from core.jobs.files import CHECKPOINT_FOLDER, LOG_FILE
from core.jobs.specs import TrainParams
from core.jobs.train import initial_weights, train_config
from core.job_store import JobStore, execution_owner, get_job_store
from core.names import FINISHED_STATES
from core.settings import Settings, get_settings
from core.storage import Storage, get_storage
from workers.tasks.context import JobCancelled, JobContext, JobFailure, JobLogHandler
from workers.tasks.rendezvous import NODE_BEAT_SECONDS, NODE_TTL_SECONDS, NodeBoard
from workers.tasks.train import job_tracker, plugin_modules

# workers.ddp and workers.elastic (torch) are imported when a node runs: a starting worker need not load torch.

NODE_TASK_NAME = "workers.tasks.nodes.run_train_node"
RESULT_WAIT_SECONDS = 30.0  # how long node 0 waits for rank 0's result from another node once the ranks ended

log = logging.getLogger("denoiser.jobs")

SendNode = Callable[[str, int, int], None]  # (job id, node, attempt)


def celery_node_sender(queue: str) -> SendNode:
    def send(job_id: str, node: int, attempt: int) -> None:
        app.send_task(NODE_TASK_NAME, args=[job_id, node, attempt], queue=queue,
                      task_id=f"{job_id}-node{node}-{attempt}-{uuid.uuid4().hex[:6]}")

    return send


def _delivery_queue(default: str) -> str:
    """The queue this task came from (a test's or an operator's), where the other nodes' tasks go too."""
    from celery import current_task

    info = getattr(getattr(current_task, "request", None), "delivery_info", None) or {}
    return info.get("routing_key") or default


# ------------------------------------------------------------------------------------------ node 0

def train_on_nodes(context: JobContext, config, params: TrainParams, send: SendNode | None = None) -> dict[str, Any]:
    """Node 0 of the job (see the module notes); returns rank 0's result."""
    from workers.ddp import free_port
    from workers.elastic import ElasticNode, advertised_host

    settings, nodes = context.settings, params.nodes
    send = send or celery_node_sender(_delivery_queue(context.record["queue"]))
    attempt = int(context.record["attempts"])
    board = NodeBoard(context.store, context.job_id, settings.job_time_limit_seconds)
    host = advertised_host(settings)
    endpoint = f"{host}:{free_port('')}"  # a port free on every interface: the rendezvous store listens on all
    tracker = job_tracker(context, config, params.track)
    if tracker is not None:
        tracker.start({}, resume_run_id=context.record.get("mlflow_run_id"))
    node = ElasticNode(config, job_id=context.job_id, node=0, nodes=nodes, endpoint=endpoint, local_addr=host,
                       settings=settings, track=params.track, run_id=tracker.run_id if tracker else None,
                       imports=plugin_modules())
    board.publish(attempt, endpoint, nodes)
    node.start()
    context.logger.info("node 0 of %d: torchrun pid %d, rendezvous %s (attempt %d)", nodes, node.process.pid,
                        endpoint, attempt)
    for other in range(1, nodes):
        send(context.job_id, other, attempt)
    supervisor = _Supervisor(board, context, nodes, attempt, send)
    stop_lock = threading.Lock()

    def stop() -> None:
        with stop_lock:  # the watchdog (cancel) and this thread (the end) may both stop the node
            node.stop()

    unregister = context.on_cancel(stop)
    supervisor.start()
    try:
        result = _node_zero_result(context, node, board, supervisor)
    except BaseException:
        if tracker is not None:
            tracker.finish("FAILED")  # KILLED when cancelled (job_tracker); a resumed attempt reopens the run
        raise
    finally:
        unregister()
        supervisor.stop()
        stop()
        context.logger.info("end of node 0's log (%s):\n%s", node.log_path, node.log_tail(40))
    board.clear(nodes)
    context.set_mlflow_run(result.get("run_id"))
    return result


def _node_zero_result(context: JobContext, node, board: NodeBoard, supervisor: _Supervisor) -> dict[str, Any]:
    from workers.ddp import RankError

    try:
        result = node.wait(context.progress)
    except RankError as error:
        context.check()  # stopped because of a cancel: say that, not "ranks failed"
        missing = supervisor.never_started()
        if missing:
            timeout = context.settings.rendezvous_timeout_seconds
            raise JobFailure("nodes_missing", f"node(s) {', '.join(map(str, missing))} of {node.nodes} never "
                             f"started: no free worker of the job's queue took them within the rendezvous "
                             f"timeout ({timeout} s); a job on {node.nodes} nodes needs {node.nodes} workers"
                             ) from error
        raise
    return result if result is not None else _result_from_another_node(board, supervisor.attempt)


def _result_from_another_node(board: NodeBoard, attempt: int) -> dict[str, Any]:
    from workers.ddp import RankError

    deadline = time.monotonic() + RESULT_WAIT_SECONDS
    while time.monotonic() < deadline:
        result = board.result(attempt)
        if result is not None:
            return result
        time.sleep(0.2)
    raise RankError(f"the ranks ended but no node relayed rank 0's result within {RESULT_WAIT_SECONDS:.0f} s")


class _Ticker(ABC):
    """A daemon thread of one node's execution that calls ``tick`` every NODE_BEAT_SECONDS until ``stop`` (or until
    ``tick`` returns True); a Redis blip only skips a tick."""

    def __init__(self, context: JobContext, name: str) -> None:
        self.context = context
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"job-{context.job_id[:8]}-{name}", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)

    @abstractmethod
    def tick(self) -> bool:
        """One look; True ends the thread."""

    def _run(self) -> None:
        while not self._stop.wait(NODE_BEAT_SECONDS):
            try:
                if self.tick():
                    return
            except Exception:  # Redis briefly unreachable: try again on the next tick
                self.context.logger.warning("%s could not reach Redis", self._thread.name, exc_info=True)


class _Supervisor(_Ticker):
    """Node 0's thread that replaces nodes whose state key lapsed (their worker died)."""

    def __init__(self, board: NodeBoard, context: JobContext, nodes: int, attempt: int, send: SendNode) -> None:
        super().__init__(context, "nodes")
        self.board, self.nodes, self.attempt, self.send = board, nodes, attempt, send
        self.seen: set[int] = set()
        self.replaced = 0

    def never_started(self) -> list[int]:
        return [node for node in range(1, self.nodes) if node not in self.seen]

    def tick(self) -> bool:
        for node in range(1, self.nodes):
            self._look_at(node)
        return False

    def _look_at(self, node: int) -> None:
        state = self.board.node(node)
        if state is not None and state["attempt"] == self.attempt:
            self.seen.add(node)
            return
        if node not in self.seen:
            return  # not started yet: the rendezvous timeout bounds the wait
        self.seen.discard(node)
        limit = self.context.settings.node_max_restarts
        if self.replaced >= limit:
            self.context.logger.error("node %d was lost; %d replacements already sent, no more", node, limit)
            return
        self.replaced += 1
        self.context.logger.warning("node %d was lost (silent for %d s); sending a replacement (%d of %d)",
                                    node, NODE_TTL_SECONDS, self.replaced, limit)
        self.send(self.context.job_id, node, self.attempt)


# -------------------------------------------------------------------------------------- nodes 1..N-1

@app.task(name=NODE_TASK_NAME, acks_late=True)
def run_train_node(job_id: str, node: int, attempt: int) -> dict[str, Any]:
    return run_node(job_id, node, attempt, get_job_store(), get_storage(), get_settings())


def run_node(job_id: str, node: int, attempt: int, store: JobStore, storage: Storage,
             settings: Settings) -> dict[str, Any]:
    """Run node ``node`` of the job's attempt ``attempt`` to its end (see the module notes)."""
    record = store.get(job_id)
    board = NodeBoard(store, job_id, settings.job_time_limit_seconds)
    published = board.rendezvous()
    if record is None or record["state"] in FINISHED_STATES or record["cancel_requested"]:
        return {"job_id": job_id, "node": node, "skipped": "finished"}
    if published is None or published["attempt"] != attempt:
        return {"job_id": job_id, "node": node, "skipped": "another attempt"}
    context = JobContext(record, store, storage, settings, execution_owner())
    handler = JobLogHandler(context.folder / LOG_FILE)
    logging.getLogger().addHandler(handler)
    try:
        return _run_node(context, board, node, attempt, published["endpoint"])
    finally:
        logging.getLogger().removeHandler(handler)
        handler.close()


def _run_node(context: JobContext, board: NodeBoard, node: int, attempt: int, endpoint: str) -> dict[str, Any]:
    from workers.ddp import RankError
    from workers.elastic import ElasticNode, advertised_host

    params = TrainParams.model_validate(context.params)
    config = train_config(params, context.storage, context.settings, context.folder / CHECKPOINT_FOLDER,
                          context.torch_device, initial_weights(params, context.storage))
    host = advertised_host(context.settings)
    elastic = ElasticNode(config, job_id=context.job_id, node=node, nodes=params.nodes, endpoint=endpoint,
                          local_addr=host, settings=context.settings, track=params.track,
                          run_id=context.record.get("mlflow_run_id"), imports=plugin_modules())
    board.mark(node, attempt, "running", context.owner)
    elastic.start()
    context.logger.info("node %d of %d started on %s: torchrun pid %d, rendezvous %s (attempt %d)", node,
                        params.nodes, host, elastic.process.pid, endpoint, attempt)
    watcher = _NodeWatcher(context, board, node, attempt, elastic)
    watcher.start()
    state = "failed"
    try:
        result = elastic.wait(context.progress)
        if result is not None:
            board.put_result(attempt, result)
        state = "done"
    except JobCancelled:
        state = "stopped"
    except RankError as error:
        state = "stopped" if context.cancelled.is_set() else "failed"
        if state == "failed":
            context.logger.error("node %d: %s", node, error)
    finally:
        watcher.stop()
        elastic.stop()
        board.mark(node, attempt, state, context.owner)
        context.logger.info("node %d ended (%s); end of its log (%s):\n%s", node, state, elastic.log_path,
                            elastic.log_tail(40))
    return {"job_id": context.job_id, "node": node, "attempt": attempt, "state": state}


class _NodeWatcher(_Ticker):
    """Keeps the node's state key alive; stops the node when the job is cancelled or finished, or node 0's
    execution was lost or another attempt took over (the job runs again)."""

    def __init__(self, context: JobContext, board: NodeBoard, node: int, attempt: int, elastic) -> None:
        super().__init__(context, f"node{node}")
        self.board, self.node, self.attempt, self.elastic = board, node, attempt, elastic

    def tick(self) -> bool:
        self.board.mark(self.node, self.attempt, "running", self.context.owner)
        reason = self._reason_to_stop()
        if reason:
            self.context.logger.info("node %d stops: %s", self.node, reason)
            self.context.cancelled.set()
            self.elastic.stop()
        return reason is not None

    def _reason_to_stop(self) -> str | None:
        store, job_id = self.context.store, self.context.job_id
        record = store.get(job_id)
        if record is None or record["state"] in FINISHED_STATES or record["cancel_requested"]:
            return "the job ended or was cancelled"
        published = self.board.rendezvous()
        if published is None or published["attempt"] != self.attempt:
            return "the job runs another attempt"
        if store.lease_holder(job_id) is None:
            # Node 0's execution is gone (its lease lapsed): recovery runs the job again, on free workers.
            return "node 0's execution was lost"
        return None
