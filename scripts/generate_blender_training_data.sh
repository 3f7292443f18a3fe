#!/usr/bin/env bash
# Renders Blender Cycles training sequences (scripts/render_blender.py; needs bpy, the 'blender' extra) and builds
# the mixed dataset the shipped 1x fused model was fine-tuned on: data/reuse's training and validation sequences
# plus these, so a model learns Cycles' frames (no jitter, z-up, its noise) beside our Mitsuba ones.
#   scenes: room_dolly and room_light (a closed room under a point light; not the open-floor scenes of
#   scripts/reproduce_blender_results.sh, which stay held out), seeds 11 and 12, 12 frames, 128x128, 1 spp,
#   128 spp references at 256x256 (--ref-scale 2: 2x references for the 2x models, and their 2x2 means, 512
#   samples a pixel, as the 1x ones) -> data/blender-train (train split);
#   data/reuse-mixed: links to data/reuse's train and validation sequences and to each Blender sequence four
#   times (so Cycles' frames are about a third of the training windows; listed once, a seventh, the same 1x
#   fine-tune scored lower on Blender's evaluation sequences).
# About 25 minutes on 2 CPU cores (the references take most of it).
# Usage: scripts/generate_blender_training_data.sh  (after generate_reuse_data.sh)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh --blender  # the project and bpy (the 'blender' extra), idempotent
RENDERS=renders/blender-train
mkdir -p "$RENDERS"
render() {  # SCENE SEED
  local out="$RENDERS/$1_s$2"
  [ -f "$out/references/frame_0011.exr" ] || .venv/bin/python scripts/render_blender.py --out "$out" --scene "$1" \
    --frames 12 --seed "$2" --size 128 --ref-spp 128 --ref-scale 2 > "$RENDERS-$1_s$2.log" 2>&1
  .venv/bin/denoiser import --layout blender-cycles "$out" --out data/blender-train --split train --overwrite > /dev/null
}
(render room_dolly 11; render room_dolly 12) &
(render room_light 11; render room_light 12) &
wait
.venv/bin/python scripts/link_datasets.py data/reuse-mixed reuse:1:train,validation blender-train:4:train
