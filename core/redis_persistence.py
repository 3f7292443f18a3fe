"""Whether the Redis this deployment uses keeps its data across its own restart: append-only file, RDB snapshots,
or neither (then a Redis restart empties the job queue, the job records and the sessions' mirrors).

/ready reports it (a warning, never "unready": the API serves all the same), and scripts/services.sh prints the
warning on start: `python -m core.redis_persistence URL` prints it and exits 0 either way.
"""

from __future__ import annotations

import sys
from typing import Literal

import redis

Persistence = Literal["aof", "rdb", "none", "unknown"]
TIMEOUT_SECONDS = 1.0


def persistence_warning(kind: Persistence) -> str | None:
    """The text an operator should read for ``kind``, None when Redis persists."""
    if kind == "none":
        return ("Redis keeps no persistence (appendonly no and no save points): a Redis restart empties the job "
                "queue, the job records and the sessions; turn on appendonly (docs/operations.md)")
    if kind == "unknown":
        return "Redis's persistence could not be read (CONFIG and INFO persistence refused or unreachable)"
    return None


def redis_persistence(client: redis.Redis) -> Persistence:
    """aof when the append-only file is on (with or without snapshots), rdb when only save points are set, none
    when neither, unknown when Redis refuses both CONFIG GET and INFO persistence or does not answer."""
    try:
        appendonly = client.config_get("appendonly").get("appendonly")
        save = client.config_get("save").get("save")
    except (redis.RedisError, OSError):
        appendonly = save = None  # managed Redis services often disable CONFIG: INFO still tells about AOF
    if appendonly is None:
        try:
            info = client.info("persistence")
        except (redis.RedisError, OSError):
            return "unknown"
        # INFO shows whether AOF is on, not whether save points are configured.
        return "aof" if int(info.get("aof_enabled", 0)) else "unknown"
    if _text(appendonly) == "yes":
        return "aof"
    return "rdb" if save is not None and _text(save).strip() else "none"


def _text(value: str | bytes) -> str:
    return value.decode() if isinstance(value, bytes) else value


def persistence_of_url(url: str) -> Persistence:
    client = redis.Redis.from_url(url, socket_connect_timeout=TIMEOUT_SECONDS, socket_timeout=TIMEOUT_SECONDS)
    try:
        return redis_persistence(client)
    finally:
        client.close()


if __name__ == "__main__":
    kind = persistence_of_url(sys.argv[1])
    warning = persistence_warning(kind)
    print(f"WARNING: {warning}" if warning else f"Redis persistence: {kind}")
