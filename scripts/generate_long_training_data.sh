#!/usr/bin/env bash
# Renders the long training sequences of the 1x fused models' last fine-tune (docs/results/findings.md): the
# training recipes of scripts/generate_reuse_data.sh with 32 frames instead of 12, so a sample of
# 24 frames shows the network a history twice as long as before; the held-out recipes stay held out.
#   data/longtrain:   train: the nine training recipes, seeds 7 and 8, 32 frames; validation: sliding_over_texture,
#                     orbiting_light, moving_highlights, textured_detail, seed 5, 32 frames; 128x128, 1x
#                     references with 256 samples; and the two Blender Cycles sequences below;
#   data/blender-long: Blender Cycles' room_dolly and room_light (scripts/render_blender.py, needs bpy), seed 11,
#                     32 frames, 128-sample 1x references;
#   data/longmix:     links to data/longtrain's sequences and to each Blender sequence twice more (scripts/
#                     link_datasets.py), so Cycles' frames are 6 of the 24 training sequences.
# About 30 minutes on 2 CPU cores (Mitsuba and Blender side by side).
# Seed 7 is also the stability suite's seed (docs/stability.md): a model trained on this set has seen
# that report's scenes, so its numbers there are not held out.
# Usage: scripts/generate_long_training_data.sh
set -euo pipefail
cd "$(dirname "$0")/.."
gen() { .venv/bin/denoiser generate --size 128 --ref-spp 256 --scales 1 --quiet --overwrite --frames 32 "$@"; }
TRAIN=(--scene diffuse_room --scene textured_detail --scene metals --scene fast_camera --scene dark_fireflies
       --scene swinging_light --scene orbiting_light --scene sliding_over_texture --scene moving_highlights)
mitsuba() {
  gen --out data/longtrain --split train --seed 7 "${TRAIN[@]}"
  gen --out data/longtrain --split validation --seed 5 --scene sliding_over_texture --scene orbiting_light \
    --scene moving_highlights --scene textured_detail
  gen --out data/longtrain --split train --seed 8 "${TRAIN[@]}"
}
blender() {
  local scene out
  for scene in room_dolly room_light; do
    out=renders/blender-long/${scene}_s11
    [ -f "$out/references/frame_0031.exr" ] || .venv/bin/python scripts/render_blender.py --out "$out" \
      --scene "$scene" --frames 32 --seed 11 --size 128 --ref-spp 128 --ref-scale 1 > "$out.log" 2>&1
    .venv/bin/denoiser import --layout blender-cycles "$out" --out data/blender-long --split train --overwrite
  done
}
mkdir -p renders/blender-long
mitsuba &
blender &
wait
# The Blender sequences join data/longtrain only after the Mitsuba renders: two writers of one manifest could race.
for scene in room_dolly room_light; do
  .venv/bin/denoiser import --layout blender-cycles "renders/blender-long/${scene}_s11" --out data/longtrain \
    --split train --overwrite
done
.venv/bin/python scripts/link_datasets.py data/longmix longtrain:1:train,validation blender-long:2:train
