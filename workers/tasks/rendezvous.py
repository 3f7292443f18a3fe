"""What the nodes of a multi-node training job tell each other through the job store's Redis.

Keys, beside the job's record (``core.job_store``; ``prefix`` as there):

    {prefix}job:<id>:rendezvous          {"attempt", "endpoint", "nodes"}: where this attempt's torchrun
                                         rendezvous is; the first node (the job's execution) publishes it
    {prefix}job:<id>:node:<n>            {"attempt", "state", "owner"}: node n's execution; "running" with a
                                         short TTL its watcher refreshes (gone: the node died), then
                                         "done" or "failed"
    {prefix}job:<id>:result:<attempt>    rank 0's result, from whichever node's torchrun ran rank 0

An attempt is the job's ``attempts`` count when its execution started: a node task of an older attempt finds
another attempt published and stops. Every key expires after the job time limit.
"""

from __future__ import annotations

import json
from typing import Any

from core.job_store import JobStore

NODE_TTL_SECONDS = 10  # a node silent this long is lost (its watcher writes every NODE_BEAT_SECONDS)
NODE_BEAT_SECONDS = 1.0


class NodeBoard:
    def __init__(self, store: JobStore, job_id: str, ttl: int) -> None:
        self.redis = store.redis
        self.base = f"{store.key(job_id)}:"
        self.ttl = ttl

    def _set(self, key: str, value: Any, ttl: int | None = None) -> None:
        self.redis.set(self.base + key, json.dumps(value), ex=ttl or self.ttl)

    def _get(self, key: str) -> Any:
        raw = self.redis.get(self.base + key)
        return None if raw is None else json.loads(raw)

    def publish(self, attempt: int, endpoint: str, nodes: int) -> None:
        for node in range(nodes):  # an earlier attempt's node states mean nothing to this one
            self.redis.delete(self.base + f"node:{node}")
        self._set("rendezvous", {"attempt": attempt, "endpoint": endpoint, "nodes": nodes})

    def rendezvous(self) -> dict[str, Any] | None:
        return self._get("rendezvous")

    def mark(self, node: int, attempt: int, state: str, owner: str) -> None:
        """Node ``node``'s state: "running" lives NODE_TTL_SECONDS unless marked again."""
        self._set(f"node:{node}", {"attempt": attempt, "state": state, "owner": owner},
                  NODE_TTL_SECONDS if state == "running" else None)

    def node(self, node: int) -> dict[str, Any] | None:
        return self._get(f"node:{node}")

    def put_result(self, attempt: int, result: dict[str, Any]) -> None:
        self._set(f"result:{attempt}", result)

    def result(self, attempt: int) -> dict[str, Any] | None:
        return self._get(f"result:{attempt}")

    def clear(self, nodes: int) -> None:
        self.redis.delete(self.base + "rendezvous", *(self.base + f"node:{node}" for node in range(nodes)))
