#!/usr/bin/env bash
# Reproduces the README's temporal-reuse results: the fused family (OIDN + learned temporal reuse) trained on
# the dataset of scripts/generate_reuse_data.sh (rendered first if missing), then evaluated on its held-out test
# recipes at 1x and 2x against OIDN (fast, balanced, high) and OIDN + TAA at the same qualities, timed in the same
# run, with side-by-side pictures of the moving-light and moving-object cases; then it ships both checkpoints as
# the repository's pretrained models (pretrained/fused-balanced-x{1,2}: weights,
# recipe and the held-out rows of these reports; scripts/ship_pretrained.py).
# On the 2-core CPU, one torch thread per training run: fused:balanced at 1x and at 2x side by side.
# Usage: scripts/reproduce_reuse_results.sh [DATA_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/reuse}
STEPS_X1=${STEPS_X1:-2000}
STEPS_X2=${STEPS_X2:-2000}
[ -f "$DATA/manifest.json" ] || bash scripts/generate_reuse_data.sh "$DATA"
train=(.venv/bin/denoiser train --data "$DATA" --method fused:balanced --crop 64 --frames-per-sample 8 --batch 4
       --lr 2e-3 --threads 1 --validate-every 250 --checkpoint-every 250 --quiet)
"${train[@]}" --scale 1 --steps "$STEPS_X1" --out runs/fused-balanced-x1 > runs-fused-balanced-x1.log 2>&1 &
"${train[@]}" --scale 2 --steps "$STEPS_X2" --out runs/fused-balanced-x2 > runs-fused-balanced-x2.log 2>&1 &
wait
mkdir -p docs/results
for scale in 1 2; do
  .venv/bin/denoiser evaluate --data "$DATA" --split test --scale "$scale" --threads 2 \
    --method "runs/fused-balanced-x$scale/best.pt" --method oidn-taa:fast --method oidn-taa:balanced \
    --method oidn-taa:high --method oidn:fast --method oidn:balanced --method oidn:high \
    --method accumulation --method accumulation:rectified --method svgf --method svgf:rectified \
    --out "docs/results/reuse_x$scale.json" | tee "docs/results/reuse_x$scale.md"
done
for scale in 1 2; do
  .venv/bin/python scripts/ship_pretrained.py "runs/fused-balanced-x$scale/best.pt" --name "fused-balanced-x$scale" \
    --data "$DATA" --dataset-script scripts/generate_reuse_data.sh --training-script scripts/reproduce_reuse_results.sh \
    --report "docs/results/reuse_x$scale.json"
done
