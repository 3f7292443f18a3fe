"""`denoiser serve`, `denoiser worker` and `denoiser mlflow-ui`: the processes of a deployment.

docker-compose.yml runs the same programs (uvicorn service.http.app:app, the Celery worker with the solo pool,
an MLflow server); these commands are the one-line way to run them on a workstation.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from cli.main import UsageError, positive_int
from core.names import QUEUES



def add_commands(commands) -> None:
    _add_serve(commands)
    _add_worker(commands)
    _add_mlflow_ui(commands)


def _port(text: str) -> int:
    port = positive_int(text)
    if port > 65535:
        import argparse

        raise argparse.ArgumentTypeError(f"a port is at most 65535, got {port}")
    return port


# ------------------------------------------------------------------------------------------------ serve

def _add_serve(commands) -> None:
    parser = commands.add_parser(
        "serve", help="run the REST API (uvicorn service.http.app:app)",
        description="Run the REST API in one uvicorn process. Settings come from DENOISER_* variables "
                    "(DENOISER_DATA_DIR, DENOISER_REDIS_URL, DENOISER_API_KEY, DENOISER_TRACKING_URI, ...). One "
                    "process on purpose: inference sessions keep their model and history in its memory (mirrored "
                    "to Redis, so a restarted server continues them).")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)")
    parser.add_argument("--port", type=_port, default=8000, help="TCP port")
    parser.add_argument("--log-level", choices=("critical", "error", "warning", "info", "debug"), default="info",
                        help="uvicorn log level")
    parser.add_argument("--reload", action="store_true", help="restart when the code changes (development)")
    parser.set_defaults(run=_run_serve)


def _run_serve(args) -> int:
    import uvicorn

    from core.deployment import check_deployment_key
    from core.settings import get_settings

    settings = get_settings()
    try:
        check_deployment_key(settings, args.host)
    except RuntimeError as error:
        raise UsageError(str(error)) from None

    # A session stream's frame is one WebSocket message: let it be as large as a POSTed frame may be.
    uvicorn.run("service.http.app:app", host=args.host, port=args.port, log_level=args.log_level, reload=args.reload,
                ws_max_size=settings.max_frame_bytes)
    return 0


# ----------------------------------------------------------------------------------------------- worker

def _add_worker(commands) -> None:
    parser = commands.add_parser(
        "worker", help="run a Celery worker for the job queues (solo pool)",
        description="Run a Celery worker of core.celery_app with the solo pool: tasks run in the worker's "
                    "main process, which is not daemonic, so training jobs can start DDP ranks (prefork children "
                    "cannot). One job at a time per worker; start more workers for more parallel jobs.")
    parser.add_argument("--queues", default="cpu", metavar="Q[,Q]",
                        help=f"comma-separated queues to consume, from {', '.join(QUEUES)}")
    parser.add_argument("--loglevel", choices=("debug", "info", "warning", "error", "critical"), default="info",
                        help="Celery log level")
    parser.add_argument("--hostname", default=None, metavar="NAME",
                        help="worker node name (default: Celery's celery@HOST)")
    parser.set_defaults(run=_run_worker)


def worker_argv(queues: str, loglevel: str, hostname: str | None = None) -> list[str]:
    """The worker arguments of ``celery -A core.celery_app``; checked queue names, always the solo pool."""
    names = [name.strip() for name in queues.split(",") if name.strip()]
    unknown = [name for name in names if name not in QUEUES]
    if not names or unknown:
        raise UsageError(f"--queues {queues!r}: choose from {', '.join(QUEUES)}"
                         + (f" (unknown: {', '.join(unknown)})" if unknown else ""))
    argv = ["worker", "--pool=solo", f"--queues={','.join(names)}", f"--loglevel={loglevel.upper()}"]
    if hostname:
        argv.append(f"--hostname={hostname}")
    return argv


def _run_worker(args) -> int:
    # This process becomes `celery -A core.celery_app worker ...` (same pid, so signals reach the worker as
    # before): the worker is named by module path, and nothing of it is imported here.
    argv = celery_argv(worker_argv(args.queues, args.loglevel, args.hostname))
    os.execv(argv[0], argv)
    return 0  # not reached, but where execv is replaced (tests)


def celery_argv(worker: list[str]) -> list[str]:
    return [sys.executable, "-m", "celery", "-A", "core.celery_app", *worker]


# -------------------------------------------------------------------------------------------- mlflow-ui

def _add_mlflow_ui(commands) -> None:
    parser = commands.add_parser(
        "mlflow-ui", help="run the MLflow UI on the service's tracking store",
        description="Run 'mlflow ui' on the tracking URI the service and workers use: DENOISER_TRACKING_URI, "
                    "else the SQLite database under DENOISER_DATA_DIR (see core/settings.py).")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on")
    parser.add_argument("--port", type=_port, default=5000, help="TCP port")
    parser.add_argument("--tracking-uri", default=None, metavar="URI",
                        help="tracking store to show instead of the resolved one")
    parser.set_defaults(run=_run_mlflow_ui)


def mlflow_ui_argv(tracking_uri: str, host: str, port: int) -> list[str]:
    return [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", tracking_uri, "--host", host,
            "--port", str(port)]


def _run_mlflow_ui(args) -> int:
    from core.settings import get_settings

    uri = args.tracking_uri or get_settings().resolved_tracking_uri()
    if uri.startswith(("http://", "https://")):
        raise UsageError(f"the tracking URI {uri} is an MLflow server already: open it in a browser")
    sqlite = "sqlite:///"  # as core.tracking.sqlite_path, without importing MLflow into this process
    if uri.startswith(sqlite):
        # A fresh data folder has no mlflow/ yet; SQLite creates the file but not its folder.
        Path(uri[len(sqlite):]).parent.mkdir(parents=True, exist_ok=True)
    print(f"MLflow UI for {uri} on http://{args.host}:{args.port}", file=sys.stderr, flush=True)
    return subprocess.call(mlflow_ui_argv(uri, args.host, args.port))
