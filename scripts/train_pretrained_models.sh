#!/usr/bin/env bash
# Trains, evaluates and ships every pretrained model of the repository (pretrained/), in one run: renders the
# dataset of scripts/generate_reuse_data.sh if it is missing, then the fused family (scripts/reproduce_reuse_results.sh:
# fused-{fast,balanced,high}-x1, fused-{fast,balanced}-x2) and the seed-paper families with int8 JNDS
# (scripts/train_pretrained_seed_models.sh). Each model's manifest records which of the two scripts trained it, the
# dataset's recipe and digest, and its held-out rows beside OIDN's. About 2 hours on 2 CPU cores.
# Usage: scripts/train_pretrained_models.sh [DATA_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/reuse}
[ -f "$DATA/manifest.json" ] || bash scripts/generate_reuse_data.sh "$DATA"
bash scripts/reproduce_reuse_results.sh "$DATA"
bash scripts/train_pretrained_seed_models.sh "$DATA"
.venv/bin/denoiser pretrained
