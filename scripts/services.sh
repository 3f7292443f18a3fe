#!/usr/bin/env bash
# Starts, stops or reports the local stack (no Docker): Redis (if nothing listens on the host and port of
# DENOISER_REDIS_URL, and that host is this one; append-only, its files in var/redis), the REST API,
# one Celery worker (queues cpu, solo pool) and the MLflow UI. Settings: DENOISER_* variables (defaults:
# data and the MLflow SQLite store under the checkout's var/, where every denoiser command finds them from any
# folder). Logs: var/logs/<name>.log; process ids: var/run/<name>.pid.
#   bash scripts/services.sh start|stop|restart|status [api|worker|mlflow]
#   bash scripts/services.sh redis-command      prints Redis's host and port, then the command that would start it
#   bash scripts/services.sh redis-check        says whether that Redis persists (start says it too)
set -euo pipefail
cd "$(dirname "$0")/.."
DATA_DIR=${DENOISER_DATA_DIR:-$PWD/var}  # absolute: the processes and the CLI resolve it alike wherever they run
API_PORT=${DENOISER_API_PORT:-8000}
MLFLOW_PORT=${DENOISER_MLFLOW_PORT:-5000}
export DENOISER_DATA_DIR=$DATA_DIR
export DENOISER_MLFLOW_UI_URL=${DENOISER_MLFLOW_UI_URL:-http://127.0.0.1:$MLFLOW_PORT}
export DRJIT_LIBLLVM_PATH=${DRJIT_LIBLLVM_PATH:-/usr/lib/x86_64-linux-gnu/libLLVM-19.so}
LOGS=$DATA_DIR/logs
RUN=$DATA_DIR/run
mkdir -p "$LOGS" "$RUN"
DENOISER=.venv/bin/denoiser

port_open() { .venv/bin/python -c "import socket,sys; socket.create_connection(('$1', $2), timeout=1).close()" 2>/dev/null; }
running() { [ -f "$RUN/$1.pid" ] && kill -0 "$(cat "$RUN/$1.pid")" 2>/dev/null; }

# Redis's host and port from DENOISER_REDIS_URL (redis://[user:password@]host[:port][/db]).
REDIS_URL=${DENOISER_REDIS_URL:-redis://127.0.0.1:6379/0}
redis_rest=${REDIS_URL#*://}; redis_rest=${redis_rest##*@}; redis_hostport=${redis_rest%%/*}
REDIS_HOST=${redis_hostport%:*}; REDIS_PORT=${redis_hostport##*:}
if [ "$REDIS_HOST" = "$redis_hostport" ]; then REDIS_PORT=6379; fi
REDIS_DIR=$DATA_DIR/redis

# Append-only persistence (as in docker-compose): queued jobs, job records and session mirrors survive a restart.
redis_command() {
  echo redis-server --daemonize yes --bind 127.0.0.1 --port "$REDIS_PORT" --dir "$(cd "$REDIS_DIR" && pwd)" \
    --appendonly yes --appendfsync everysec
}

ensure_redis() {
  mkdir -p "$REDIS_DIR"
  if port_open "$REDIS_HOST" "$REDIS_PORT"; then return; fi
  case "$REDIS_HOST" in
    127.0.0.1|localhost) ;;
    *) echo "[services] Redis at $REDIS_HOST:$REDIS_PORT (DENOISER_REDIS_URL) does not answer; start it there" >&2; exit 1 ;;
  esac
  echo "[services] Redis is not running on 127.0.0.1:$REDIS_PORT: starting it (append-only, in $REDIS_DIR)"
  command -v redis-server >/dev/null 2>&1 || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq redis-server; }
  $(redis_command)
  for _ in $(seq 50); do port_open "$REDIS_HOST" "$REDIS_PORT" && return; sleep 0.2; done
  echo "[services] Redis did not start" >&2; exit 1
}

# A Redis that was already there (the machine's own) may keep nothing across its restart: the job queue, job
# records and sessions would go with it. Said on every start; /ready says it too (redis_persistence).
redis_check() {
  local said
  said=$(.venv/bin/python -m core.redis_persistence "$REDIS_URL")
  case "$said" in
    WARNING*) echo "[services] $said" >&2 ;;
    *) echo "[services] $said" ;;
  esac
}

start_one() {  # name command...
  local name=$1; shift
  if running "$name"; then echo "[services] $name already running (pid $(cat "$RUN/$name.pid"))"; return; fi
  # Its own session (setsid): stopping it ends its children too (DDP ranks, uvicorn workers).
  setsid nohup "$@" >> "$LOGS/$name.log" 2>&1 < /dev/null &
  echo $! > "$RUN/$name.pid"
  echo "[services] started $name (pid $!, log $LOGS/$name.log)"
}

stop_one() {
  local name=$1
  if ! running "$name"; then rm -f "$RUN/$name.pid"; return; fi
  local pid; pid=$(cat "$RUN/$name.pid")
  kill -TERM -- "-$pid" 2>/dev/null || kill -TERM "$pid" 2>/dev/null || true
  for _ in $(seq 100); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
  kill -KILL -- "-$pid" 2>/dev/null || true
  rm -f "$RUN/$name.pid"
  echo "[services] stopped $name"
}

wait_http() {  # url what
  for _ in $(seq 120); do
    if .venv/bin/python -c "import httpx,sys; sys.exit(0 if httpx.get('$1', timeout=2).status_code < 500 else 1)" 2>/dev/null; then return; fi
    sleep 0.5
  done
  echo "[services] $2 did not answer at $1: see $LOGS" >&2; exit 1
}

start() {
  local which=${1:-all}
  ensure_redis
  redis_check
  if [ "$which" = all ] || [ "$which" = mlflow ]; then
    start_one mlflow "$DENOISER" mlflow-ui --port "$MLFLOW_PORT"
  fi
  if [ "$which" = all ] || [ "$which" = worker ]; then
    start_one worker "$DENOISER" worker --queues cpu --loglevel info
  fi
  if [ "$which" = all ] || [ "$which" = api ]; then
    start_one api "$DENOISER" serve --port "$API_PORT"
    wait_http "http://127.0.0.1:$API_PORT/health" "the API"
  fi
  if [ "$which" = all ] || [ "$which" = mlflow ]; then wait_http "http://127.0.0.1:$MLFLOW_PORT/" "the MLflow UI"; fi
}

stop() {
  local which=${1:-all}
  for name in api worker mlflow; do
    if [ "$which" = all ] || [ "$which" = "$name" ]; then stop_one "$name"; fi
  done
}

status() {
  for name in api worker mlflow; do
    if running "$name"; then echo "$name: running (pid $(cat "$RUN/$name.pid"))"; else echo "$name: stopped"; fi
  done
}

case "${1:-}" in
  start) start "${2:-all}" ;;
  stop) stop "${2:-all}" ;;
  restart) stop "${2:-all}"; start "${2:-all}" ;;
  status) status ;;
  redis-command) mkdir -p "$REDIS_DIR"; echo "$REDIS_HOST $REDIS_PORT"; redis_command ;;
  redis-check) redis_check ;;
  *) echo "usage: scripts/services.sh start|stop|restart|status [api|worker|mlflow]" >&2; exit 2 ;;
esac
