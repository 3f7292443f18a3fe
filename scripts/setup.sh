#!/usr/bin/env bash
# Sets up a fresh machine and runs the main job locally (no Docker): installs the project, starts Redis if it
# is not running, starts the REST API, a Celery worker and the MLflow UI (scripts/services.sh), then, through
# the API, renders a small dataset with Mitsuba 3, trains a small model, registers it with the alias `champion`,
# evaluates it next to the pretrained fused model, SVGF and OIDN on a held-out scene and streams the held-out
# sequence through inference sessions (scripts/demo_pipeline.py). Before that it registers the pretrained models
# shipped in pretrained/ in MLflow with the alias `pretrained` (denoiser pretrained --register; idempotent).
# The services keep running; the URLs are printed at the end.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export DENOISER_DATA_DIR=${DENOISER_DATA_DIR:-$PWD/var}  # the checkout's var/, the settings' default too
API_PORT=${DENOISER_API_PORT:-8000}
MLFLOW_PORT=${DENOISER_MLFLOW_PORT:-5000}
bash scripts/services.sh start
# The pretrained models shipped in pretrained/, registered once with the alias `pretrained` (a rerun finds them).
.venv/bin/denoiser pretrained --register
.venv/bin/python scripts/demo_pipeline.py --url "http://127.0.0.1:$API_PORT" --out "$DENOISER_DATA_DIR/demo-output"
cat <<MSG
[setup] done. Running now (stop them with: bash scripts/services.sh stop):
        API        http://127.0.0.1:$API_PORT   (OpenAPI docs: http://127.0.0.1:$API_PORT/docs)
        MLflow UI  http://127.0.0.1:$MLFLOW_PORT
        worker     queue cpu, log $DENOISER_DATA_DIR/logs/worker.log
        data       $DENOISER_DATA_DIR/ (datasets, jobs, results, MLflow store); streamed frames: $DENOISER_DATA_DIR/demo-output
        try        .venv/bin/denoiser models; .venv/bin/denoiser jobs
MSG
