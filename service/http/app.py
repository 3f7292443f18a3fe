"""The FastAPI application: `uvicorn service.http.app:app` (or `denoiser serve`).

Routers live in service/http/routes/, one module per resource; every one but /health and /ready needs the API key
when one is configured (the schema and the docs pages too, unless DENOISER_PUBLIC_API_DOCS: service/http/api_docs.py). Errors share one JSON shape (service/http/errors.py).
"""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI

from service.http.api_docs import install_api_docs
from service.http.auth import UNAUTHORIZED_RESPONSE, require_api_key
from service.http.errors import install_error_handlers
from service.http.metrics import AppMetrics, RequestMetrics
from service.http.request_limits import BodyReadTimeout
from service.http.routes import datasets, health, jobs, metrics, models, session_stream, sessions
from core.settings import get_settings

API_VERSION = "1.0"

DESCRIPTION = """
Trains and serves real-time neural denoisers (and 2x upscalers) for path-traced frames.

* **/datasets**: upload EXR frame sequences (a zip or tar of sequence folders, or frame by frame), inspect, delete.
* **/jobs**: `generate`, `train`, `evaluate`, `benchmark`, `infer` and `fit` (right-sizing) jobs run by Celery
  workers; progress, logs, MLflow run, cancel; `infer` results downloadable as EXR, reports, charts and fit ladders
  as artifacts.
* **/models**: models registered in MLflow, their versions, metrics and aliases.
* **/sessions**: stream frame bundles (EXR) through a model (or `"model": "auto"`: the smallest registered version
  that meets a quality or time constraint); the server keeps each session's temporal history. A session's frames
  can also go over one WebSocket, `/sessions/{session_id}/stream`, as raw arrays (README, "Streaming a session
  over a WebSocket"; not in this schema).
* **/metrics**: Prometheus metrics (requests, session frames and step times, open sessions, jobs, queue depths).

Errors: `{"error": {"code", "message", "details"}}` with a 4xx status for the caller's mistakes.
Authentication: header `X-API-Key` when the server has `DENOISER_API_KEY` set.
"""


@asynccontextmanager
async def _lifespan(app: FastAPI):
    from core.deployment import check_deployment_key
    from service.sessions.store import get_session_store
    from core.settings import get_settings
    from core.storage import get_storage

    check_deployment_key(get_settings())  # before anything starts: an exposed API without a real key must not run
    get_storage()
    store = get_session_store()
    store.add_metrics(app.state.metrics.sessions)
    yield
    store.remove_metrics(app.state.metrics.sessions)
    store.close()
    app.state.metrics.close()


def create_app() -> FastAPI:
    # FastAPI's own /docs and /redoc load their scripts from a CDN, and its /openapi.json is public:
    # install_api_docs serves all three from the app, behind the API key.
    app = FastAPI(title="denoiser-service", version=API_VERSION, description=DESCRIPTION, lifespan=_lifespan,
                  openapi_url=None, docs_url=None, redoc_url=None)
    install_error_handlers(app)
    install_api_docs(app)
    app.add_middleware(BodyReadTimeout, timeout_seconds=get_settings().body_read_timeout_seconds)
    # Added last, so outermost: it times every answer, the body-timeout's 408 included.
    app.state.metrics = AppMetrics()
    app.add_middleware(RequestMetrics, histogram=app.state.metrics.requests)
    app.include_router(health.router)
    protected = [Depends(require_api_key)]
    for module in (datasets, jobs, metrics, models, sessions):
        app.include_router(module.router, dependencies=protected, responses={401: UNAUTHORIZED_RESPONSE})
    # The session WebSocket checks the API key itself (it answers with a close code, not an HTTP error).
    app.include_router(session_stream.router)
    return app


app = create_app()
