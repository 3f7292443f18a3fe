#!/usr/bin/env bash
# Trains, evaluates and ships the pretrained models of the four seed-paper families (WSKPN, AFN, MUNet, JNDS:
# each one's default preset at 1x and 2x) and int8 JNDS (quantization-aware fine-tuning of the float32 JNDS at
# 2x), on the dataset of scripts/generate_reuse_data.sh (rendered first if missing): the same data, recipes and
# held-out test split as the shipped fused models. Then one evaluation per scale on the test split (recipes never
# seen in training) with OIDN and OIDN + TAA timed in the same run, whose rows go into each manifest.
# On the 2-core CPU, one torch thread per run, two runs side by side. The step counts are short (these are
# starting points for fine-tuning, not the families' best: the other reproduce scripts train the same
# presets 5-40x longer): about 35 minutes of training on a busy machine (WSKPN 8 minutes per scale), 10 of
# evaluation, then every one shipped again with its history rectified.
# Usage: scripts/train_pretrained_seed_models.sh [DATA_DIR]   (SKIP_TRAINED=1 keeps runs that have best.pt)
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/reuse}
[ -f "$DATA/manifest.json" ] || bash scripts/generate_reuse_data.sh "$DATA"
train() {  # METHOD SCALE STEPS [extra options]
  local method=$1 scale=$2 steps=$3 name
  shift 3
  name=$(echo "$method" | tr ':' '-')-x$scale
  if [ -n "${SKIP_TRAINED:-}" ] && [ -f "runs/$name/best.pt" ]; then return; fi
  .venv/bin/denoiser train --data "$DATA" --method "$method" --scale "$scale" --steps "$steps" --crop 48 \
    --frames-per-sample 4 --batch 4 --threads 1 --validate-every $((steps / 4)) --checkpoint-every $((steps / 4)) \
    --quiet --out "runs/$name" "$@" > "runs-$name.log" 2>&1
}
# Two lanes of about equal length; the int8 fine-tune needs the float32 JNDS at 2x first.
(train wskpn:s 1 600 --temporal-weight 0.5; train wskpn:s 2 600 --temporal-weight 0.5
 train afn:m 1 200 --temporal-weight 0.5; train afn:m 2 200 --temporal-weight 0.5
 train munet:s 1 100; train munet:s 2 100) &
(train jnds:s 2 500
 train jnds:s-int8 2 60 --init-from runs/jnds-s-x2/best.pt --lr 2e-4 --warmup-steps 10
 train jnds:s 1 150) &
wait
mkdir -p docs/results var/results
baselines=(--method oidn:balanced --method oidn:high --method oidn-taa:balanced --method oidn-taa:high)
evaluate() {  # SCALE RUN...
  local scale=$1 methods=()
  shift
  for run in "$@"; do methods+=(--method "runs/$run/best.pt"); done
  .venv/bin/denoiser evaluate --data "$DATA" --split test --scale "$scale" --threads 2 "${methods[@]}" \
    "${baselines[@]}" --out "docs/results/seed_models_x$scale.json" | tee "docs/results/seed_models_x$scale.md"
}
evaluate 1 wskpn-s-x1 afn-m-x1 munet-s-x1 jnds-s-x1
evaluate 2 wskpn-s-x2 afn-m-x2 munet-s-x2 jnds-s-x2 jnds-s-int8-x2
ship=(.venv/bin/python scripts/ship_pretrained.py --data "$DATA" --dataset-script scripts/generate_reuse_data.sh
      --training-script scripts/train_pretrained_seed_models.sh)
for run in wskpn-s-x1 afn-m-x1 munet-s-x1 jnds-s-x1; do
  "${ship[@]}" "runs/$run/best.pt" --name "$run" --report var/results/seed_models_x1.json
done
for run in wskpn-s-x2 afn-m-x2 munet-s-x2 jnds-s-x2; do
  "${ship[@]}" "runs/$run/best.pt" --name "$run" --report var/results/seed_models_x2.json
done
"${ship[@]}" runs/jnds-s-int8-x2/best.pt --name jnds-s-int8-x2 --stage runs/jnds-s-x2/best.pt \
  --report var/results/seed_models_x2.json
# The seed models run with their history rectified (docs/methods.md, "History rectification for the seed
# methods"): the shipped weights are copied to a scratch folder with the setting, evaluated beside the models without
# it, and shipped again with that report (the same weights; only the setting changes).
rm -rf runs/rectify && mkdir -p runs/rectify && cp -r pretrained runs/rectify/pretrained
rectify() {  # REPORT SCALE NAME...
  local report=$1 scale=$2 methods=() name
  shift 2
  for name in "$@"; do
    .venv/bin/python scripts/ship_pretrained.py "runs/rectify/pretrained/$name/model.pt" --name "$name" \
      --after-shipped "$name" --rectify-history --root runs/rectify/pretrained
    methods+=(--method "$name" --method "runs/rectify/pretrained/$name/model.pt")
  done
  .venv/bin/denoiser evaluate --data "$DATA" --split test --scale "$scale" --threads 2 "${methods[@]}" \
    "${baselines[@]}" --out "docs/results/$report.json" | tee "docs/results/$report.md"
  for name in "$@"; do
    .venv/bin/python scripts/ship_pretrained.py "pretrained/$name/model.pt" --name "$name" --after-shipped "$name" \
      --rectify-history --report "docs/results/$report.json" --report-source "runs/rectify/pretrained/$name/model.pt"
  done
}
rectify seed_models_rectified_x1 1 wskpn-s-x1 afn-m-x1
rectify seed_models_rectified_x2 2 wskpn-s-x2 afn-m-x2
rectify seed_models_rectified_jnds_x1 1 jnds-s-x1
rectify seed_models_rectified_jnds_x2 2 jnds-s-x2 jnds-s-int8-x2
rectify seed_models_rectified_munet_x1 1 munet-s-x1
rectify seed_models_rectified_munet_x2 2 munet-s-x2
