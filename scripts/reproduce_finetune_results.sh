#!/usr/bin/env bash
# Reproduces the fine-tuning result (docs/results/finetune_user.md): a shipped model adapted to a user's own
# renderer through the REST API, against the shipped model as it is and against training from scratch with the same
# budget, on a held-out scene of that renderer.
#   1. the user's data: Blender Cycles renders (scripts/render_blender.py; needs bpy, the 'blender' extra) of
#      procedural scenes: train orbit (seed 1) and pan (seed 1), validation orbit (seed 2), test moving_object
#      (seed 3, a scene recipe the training never sees), imported with the blender-cycles layout;
#   2. the local stack (scripts/services.sh) and the pretrained models registered (alias `pretrained`);
#   3. the dataset uploaded, then two train jobs of the same method, steps, crops, batch and data: one with
#      init_from the pretrained fused-balanced-x1, one from random weights;
#   4. one evaluate job on the test split: the pretrained model, both trained models, OIDN and OIDN + TAA, timed
#      in the same run; its report is copied to docs/results/finetune_user.{json,md}.
# About 25 minutes on 2 CPU cores (rendering 10, each training about 4).
# Usage: scripts/reproduce_finetune_results.sh   (STEPS=300 RENDERS=renders/user DATA=data/user)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh --blender  # the project and bpy (the 'blender' extra), idempotent
RENDERS=${RENDERS:-renders/user}
DATA=${DATA:-data/user}
STEPS=${STEPS:-300}
URL=http://127.0.0.1:${DENOISER_API_PORT:-8000}
DENOISER=.venv/bin/denoiser
export DENOISER_URL=$URL

render() {  # NAME SCENE FRAMES SEED
  local last
  last=$(printf '%s/%s/references/frame_%04d.exr' "$RENDERS" "$1" $(($3 - 1)))
  [ -f "$last" ] || .venv/bin/python scripts/render_blender.py --out "$RENDERS/$1" --scene "$2" --frames "$3" \
    --seed "$4" --size 128 --ref-spp 256 > "$RENDERS-$1.log" 2>&1
  $DENOISER import --layout blender-cycles "$RENDERS/$1" --out "$DATA" --split "$5" --overwrite > /dev/null
}
mkdir -p "$RENDERS"
render orbit_s1 orbit 12 1 train
render pan_s1 pan 12 1 train
render orbit_s2 orbit 12 2 validation
render moving_object_s3 moving_object 16 3 test

bash scripts/services.sh start
$DENOISER pretrained --register
dataset=$($DENOISER upload "$DATA" --json | .venv/bin/python -c 'import json, sys; print(json.load(sys.stdin)["id"])')
echo "uploaded $DATA as dataset $dataset"

# The same budget for both: method, steps, crop, batch, frames per sample, validation; each its usual rate.
train=(--param dataset="$dataset" --param method=fused:balanced --param steps="$STEPS" --param crop=64
       --param batch=4 --param frames_per_sample=8 --param validate_every=100 --param checkpoint_every=100
       --param warmup_steps=10 --progress lines --follow)
$DENOISER submit train "${train[@]}" --param init_from=fused-balanced-x1 --param lr=5e-4 \
  --param register_as=user-fused-finetuned
$DENOISER submit train "${train[@]}" --param lr=2e-3 --param register_as=user-fused-scratch

job=$($DENOISER submit evaluate --param dataset="$dataset" --param split=test --param scale=1 \
  --param methods=fused-balanced-x1 --param methods=models:/user-fused-finetuned \
  --param methods=models:/user-fused-scratch --param methods=oidn:high --param methods=oidn:balanced \
  --param methods=oidn-taa:balanced --param methods=oidn-taa:high --param threads=2 --progress none --follow \
  | grep -o 'job [0-9a-f-]*' | head -1 | cut -d' ' -f2)
mkdir -p docs/results var/results
for name in report.json report.md; do
  curl -sf "$URL/jobs/$job/artifacts/$name" -o "docs/results/finetune_user.${name#report.}"
done
cat docs/results/finetune_user.md
