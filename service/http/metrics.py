"""The API's Prometheus metrics: one registry per app, the request middleware and what /metrics reads at a scrape.

Counted as things happen: requests (ASGI middleware, labelled by the route's template, never the raw path), and,
through the session store's metrics interface (service.sessions.metrics), frames, step times and failed mirror
writes. Read at each scrape: open sessions, job records by kind and state, and each Celery queue's length in Redis;
a source that cannot be read is left out and its ``denoiser_metrics_source_up`` is 0, the rest is still served.

The registry belongs to the app, not to prometheus_client's global default: two apps in one process (tests) count
apart. The API is one process by design (sessions live in its memory); each API process, if there are several,
is its own scrape target. Series and labels: docs/operations.md, "Metrics".
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator

import redis
from kombu.transport.redis import PRIORITY_STEPS, Channel
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import GaugeMetricFamily, Metric
from redis.backoff import NoBackoff
from redis.retry import Retry
from starlette.routing import Match, Mount, Route

from core.job_store import JobStore
from core.names import QUEUES
from service.sessions.metrics import MIRROR_DELETE, MIRROR_WRITE
from service.sessions.store import SessionStore

log = logging.getLogger("denoiser.api")

UNMATCHED_ROUTE = "unmatched"  # a request no route took (404): one label value, whatever the path
OTHER_METHOD = "other"
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
REQUEST_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)
STEP_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
REDIS_TIMEOUT_SECONDS = 1.0  # a scrape reads Redis: a hung Redis must not hang the scrape


class SessionCounters:
    """The session store's metrics sink (service.sessions.metrics.SessionMetrics) on one app's registry."""

    def __init__(self, registry: CollectorRegistry) -> None:
        self.frames = Counter("denoiser_session_frames", "Frames stepped by sessions", ["model"], registry=registry)
        self.step_seconds = Histogram("denoiser_session_step_seconds", "Time of one session frame's method.step",
                                      ["model"], buckets=STEP_BUCKETS, registry=registry)
        self.mirror_failures = Counter("denoiser_session_mirror_failures",
                                       "Failed writes (or deletes) of a session's Redis copy", ["operation"],
                                       registry=registry)
        for operation in (MIRROR_WRITE, MIRROR_DELETE):
            self.mirror_failures.labels(operation)  # shown as 0 before the first failure, so rate() has a start

    def frame_processed(self, model: str, step_seconds: float) -> None:
        self.frames.labels(model).inc()
        self.step_seconds.labels(model).observe(step_seconds)

    def mirror_failed(self, operation: str) -> None:
        self.mirror_failures.labels(operation).inc()


class AppMetrics:
    """Everything one app counts, and the Redis client its scrapes read with."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Histogram("denoiser_http_request_duration_seconds", "HTTP requests by route template",
                                  ["method", "route", "status"], buckets=REQUEST_BUCKETS, registry=self.registry)
        self.sessions = SessionCounters(self.registry)
        self._clients: dict[str, redis.Redis] = {}

    def job_store(self, redis_url: str) -> JobStore:
        """A job store on ``redis_url`` with short timeouts (the routes' store waits as long as Redis takes)."""
        client = self._clients.get(redis_url)
        if client is None:
            client = self._clients[redis_url] = redis.Redis.from_url(
                redis_url, decode_responses=True, socket_timeout=REDIS_TIMEOUT_SECONDS,
                socket_connect_timeout=REDIS_TIMEOUT_SECONDS, retry=Retry(NoBackoff(), 0))
        return JobStore(client)

    def scrape(self, sessions: SessionStore, jobs: JobStore) -> _Scrape:
        """What ``prometheus_client.generate_latest`` writes for one scrape: the counted series and the ones read
        now from ``sessions`` and ``jobs`` (its Redis also holds the Celery queues)."""
        return _Scrape(self.registry, sessions, jobs)

    def close(self) -> None:
        for client in self._clients.values():
            client.close()
        self._clients.clear()


class _Scrape:
    def __init__(self, registry: CollectorRegistry, sessions: SessionStore, jobs: JobStore) -> None:
        self.registry, self.sessions, self.jobs = registry, sessions, jobs

    def collect(self) -> Iterator[Metric]:
        yield from self.registry.collect()
        up = GaugeMetricFamily("denoiser_metrics_source_up", "1 when this scrape could read the source, else 0 "
                               "(its series are left out)", labels=["source"])
        for source, read in (("sessions", self._sessions), ("jobs", self._jobs), ("queues", self._queues)):
            try:
                family = read()
            except (redis.RedisError, OSError, ValueError) as error:
                log.warning("/metrics: could not read %s: %s: %s", source, type(error).__name__, error)
                up.add_metric([source], 0)
                continue
            up.add_metric([source], 1)
            yield family
        yield up

    def _sessions(self) -> Metric:
        family = GaugeMetricFamily("denoiser_sessions_active", "Open inference sessions (not expired)")
        family.add_metric([], self.sessions.count())
        return family

    def _jobs(self) -> Metric:
        family = GaugeMetricFamily("denoiser_jobs", "Job records by kind and state", labels=["kind", "state"])
        for (kind, state), count in sorted(self.jobs.counts().items()):
            family.add_metric([kind, state], count)
        return family

    def _queues(self) -> Metric:
        family = GaugeMetricFamily("denoiser_queue_depth", "Jobs waiting in each Celery queue (not yet taken by a "
                                   "worker)", labels=["queue"])
        pipe = self.jobs.redis.pipeline(transaction=False)
        for queue in QUEUES:
            for key in queue_keys(queue):
                pipe.llen(key)
        lengths = iter(pipe.execute())
        for queue in QUEUES:
            family.add_metric([queue], sum(next(lengths) for _ in queue_keys(queue)))
        return family


def queue_keys(queue: str) -> list[str]:
    """The Redis lists that hold a Celery queue's messages: the queue's name, and one per priority step above 0
    (kombu's Redis transport keeps a message sent with a priority in ``<queue><sep><step>``)."""
    return [queue if step == 0 else f"{queue}{Channel.sep}{step}" for step in PRIORITY_STEPS]


class RequestMetrics:
    """ASGI middleware: each HTTP request's duration, by method, route template and status (WebSockets pass)."""

    def __init__(self, app, histogram: Histogram, clock: Callable[[], float] = time.perf_counter) -> None:
        self.app, self.histogram, self.clock = app, histogram, clock

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 500  # what the client gets when the app raises before answering
        start = self.clock()

        async def send_status(message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = route_template(scope)
            method = scope["method"] if scope["method"] in METHODS else OTHER_METHOD
            self.histogram.labels(method, route, str(status)).observe(self.clock() - start)


def route_template(scope) -> str:
    """The template of the route that took the request (``/sessions/{session_id}/frames``), or UNMATCHED_ROUTE."""
    # FastAPI writes its API route into the scope it is given (this one); its own pages (/docs, /openapi.json) and
    # mounts it does not, so those are matched here against the app's top-level routes.
    route = scope.get("route")
    if route is not None and getattr(route, "path", None):
        return route.path
    app = scope.get("app")
    for candidate in getattr(getattr(app, "router", None), "routes", ()):
        if isinstance(candidate, (Route, Mount)) and candidate.matches(scope)[0] is not Match.NONE:
            return candidate.path
    return UNMATCHED_ROUTE
