#!/usr/bin/env bash
# Sets up a fresh machine and runs the main job locally (no Docker): installs the project, makes sure
# Redis runs, renders a small dataset with Mitsuba 3 (summary and a picture of one frame), trains a small
# model on it and evaluates it on the held-out scene against SVGF and OIDN.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh

if ! .venv/bin/python - <<'PY' 2>/dev/null
import socket; socket.create_connection(("127.0.0.1", 6379), timeout=1).close()
PY
then
  echo "[setup] Redis is not running on 127.0.0.1:6379: starting it"
  command -v redis-server >/dev/null 2>&1 || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq redis-server; }
  redis-server --daemonize yes --bind 127.0.0.1 --port 6379 --save "" --appendonly no
fi

DATA=${DATA_DIR:-data}/demo
echo "[setup] rendering the demo dataset into $DATA"
.venv/bin/denoiser generate --scene diffuse_room --scene moving_light --frames 8 --size 64 --ref-spp 256 \
  --seed 1 --split train --out "$DATA" --overwrite
.venv/bin/denoiser generate --scene diffuse_room --frames 4 --size 64 --ref-spp 256 \
  --seed 5 --split validation --out "$DATA" --overwrite
.venv/bin/denoiser generate --scene glass --frames 8 --size 64 --ref-spp 256 \
  --seed 2 --split test --out "$DATA" --overwrite
.venv/bin/denoiser preview "$DATA/glass_s2" --index 4 --out "$DATA/preview.png"

echo "[setup] training a small WSKPN on the demo data (tracked in MLflow: mlruns/mlflow.db)"
.venv/bin/denoiser train --data "$DATA" --method wskpn:xs --steps 150 --crop 32 --batch 4 --no-resume \
  --out runs/demo-wskpn-xs --tracking-uri "sqlite:///$PWD/mlruns/mlflow.db"
echo "[setup] evaluating it on the held-out test scene against SVGF and OIDN"
.venv/bin/denoiser evaluate --data "$DATA" --split test --method runs/demo-wskpn-xs/best.pt --method svgf \
  --method oidn:high --no-vdp --quiet --out "$DATA/evaluation.json"
echo "[setup] done: dataset in $DATA, picture of one frame in $DATA/preview.png, model in runs/demo-wskpn-xs,"
echo "        evaluation in $DATA/evaluation.json; MLflow UI: .venv/bin/mlflow ui --backend-store-uri sqlite:///$PWD/mlruns/mlflow.db"
