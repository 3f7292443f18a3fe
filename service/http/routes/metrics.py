"""/metrics: the API's Prometheus metrics in the text format (service/http/metrics.py; series: docs/operations.md).

Behind the API key like the resources (a scraper sends X-API-Key). Always 200: a source that cannot be read at
this scrape (Redis down) is reported by ``denoiser_metrics_source_up`` instead of failing the whole scrape.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.concurrency import run_in_threadpool

from core.settings import Settings, get_settings
from service.http.metrics import AppMetrics
from service.sessions.store import SessionStore, get_session_store

router = APIRouter(tags=["metrics"])


def app_metrics(request: Request) -> AppMetrics:
    return request.app.state.metrics


@router.get("/metrics", response_class=Response, summary="Prometheus metrics",
            responses={200: {"description": "Prometheus text exposition format",
                             "content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}}}})
async def metrics(metrics: Annotated[AppMetrics, Depends(app_metrics)],
                  sessions: Annotated[SessionStore, Depends(get_session_store)],
                  settings: Annotated[Settings, Depends(get_settings)]) -> Response:
    """Requests by route, session frames and step times by model, open sessions, jobs by kind and state, Celery
    queue depths."""
    # The scrape reads Redis (blocking calls): off the event loop, as the sync routes run.
    body = await run_in_threadpool(generate_latest, metrics.scrape(sessions, metrics.job_store(settings.redis_url)))
    return Response(body, media_type=CONTENT_TYPE_LATEST)
