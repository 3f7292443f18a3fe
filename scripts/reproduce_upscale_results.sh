#!/usr/bin/env bash
# Reproduces the joint denoising + 2x upscaling table (docs/results/upscale_x2.md) and picture. On the 2-core CPU,
# one torch thread per run: MUNet and JNDS train side by side at scale 2 (about 35 minutes), then WSKPN at 1x (its
# network runs at render resolution: "WSKPN + bicubic" at 2x) beside int8 JNDS (quantization-aware
# fine-tuning from the float32 JNDS), then everything is evaluated on the held-out test scenes at 2x against
# OIDN-high + bicubic and accumulation + bicubic, and one frame is drawn side by side.
# Needs the dataset of scripts/generate_benchmark_data.sh (references at 2x with albedos).
# Usage: scripts/reproduce_upscale_results.sh [DATA_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/bench}
MUNET_STEPS=${MUNET_STEPS:-2500}
JNDS_STEPS=${JNDS_STEPS:-4000}
WSKPN_STEPS=${WSKPN_STEPS:-1500}
INT8_STEPS=${INT8_STEPS:-400}
train=(.venv/bin/denoiser train --data "$DATA" --crop 48 --frames-per-sample 4 --batch 4 --threads 1 --quiet)
"${train[@]}" --scale 2 --method munet:s --steps "$MUNET_STEPS" --validate-every 250 --checkpoint-every 250 \
  --out runs/munet-s-x2 > runs-munet-s-x2.log 2>&1 &
"${train[@]}" --scale 2 --method jnds:s --steps "$JNDS_STEPS" --validate-every 500 --checkpoint-every 500 \
  --out runs/jnds-s-x2 > runs-jnds-s-x2.log 2>&1 &
wait
"${train[@]}" --scale 2 --method jnds:s-int8 --init-from runs/jnds-s-x2/best.pt --steps "$INT8_STEPS" --lr 2e-4 \
  --warmup 20 --validate-every 100 --checkpoint-every 100 --out runs/jnds-s-int8-x2 > runs-jnds-s-int8-x2.log 2>&1 &
"${train[@]}" --scale 1 --method wskpn:s --steps "$WSKPN_STEPS" --temporal-weight 0.5 --validate-every 500 \
  --checkpoint-every 500 --out runs/wskpn-s-short > runs-wskpn-s-short.log 2>&1 &
wait
mkdir -p docs/results var/results
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 2 --threads 2 \
  --method runs/munet-s-x2/best.pt --method runs/jnds-s-x2/best.pt --method runs/jnds-s-int8-x2/best.pt \
  --method runs/wskpn-s-short/best.pt --method accumulation --method svgf --method identity --method oidn:high \
  --out var/results/upscale_x2.json | tee docs/results/upscale_x2.md
.venv/bin/denoiser compare --data "$DATA" --sequence glass_s4 --frame -1 --scale 2 \
  --method runs/munet-s-x2/best.pt=MUNet --method runs/jnds-s-x2/best.pt=JNDS \
  --method oidn:high=OIDN-high+bicubic --zoom 96,96,80 --out docs/upscale_x2.png
