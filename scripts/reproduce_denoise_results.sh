#!/usr/bin/env bash
# Reproduces the denoising (1x) table (docs/results/denoise_x1.md): trains WSKPN and AFN for about 30 minutes each
# on the 2-core CPU (the two runs side by side, one torch thread each), then evaluates them on the held-out test
# scenes against the baselines and OIDN. Needs the dataset of scripts/generate_benchmark_data.sh.
# Usage: scripts/reproduce_denoise_results.sh [DATA_DIR] [STEPS]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/bench}
STEPS=${2:-4000}
common=(--data "$DATA" --steps "$STEPS" --crop 64 --frames-per-sample 4 --batch 4 --threads 1
        --temporal-weight 0.5 --validate-every 500 --checkpoint-every 500 --quiet)
.venv/bin/denoiser train "${common[@]}" --method wskpn:s --out runs/wskpn-s > runs-wskpn-s.log 2>&1 &
.venv/bin/denoiser train "${common[@]}" --method afn:m --out runs/afn-m > runs-afn-m.log 2>&1 &
wait
mkdir -p docs/results var/results
.venv/bin/denoiser evaluate --data "$DATA" --split test --threads 2 \
  --method runs/wskpn-s/best.pt --method runs/afn-m/best.pt --method accumulation --method svgf \
  --method identity --method oidn:fast --method oidn:balanced --method oidn:high \
  --out var/results/denoise_x1.json | tee docs/results/denoise_x1.md
