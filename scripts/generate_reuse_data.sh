#!/usr/bin/env bash
# Renders the dataset the temporal-reuse results use (the `fused` family against OIDN and OIDN + TAA): many
# short training sequences, the failure modes of temporal reuse among them, and five recipes held out whole.
#   train:      diffuse_room, textured_detail, metals, fast_camera, dark_fireflies, swinging_light,
#               orbiting_light, sliding_over_texture, moving_highlights (3 seeds each, and a fourth without
#               sub-pixel jitter: every sample at the pixel centre, as renderers without TAA jitter write frames)
#   validation: diffuse_room, orbiting_light (another seed)
#   test:       glass, moving_light, camera_cut, moving_object, visible_emitter (recipes never seen in training:
#               a moving visible light, a circling light, an object sliding over a textured wall, a cut, glass)
# 128x128 render resolution, references at 1x and 2x (256 spp at 256x256). About 35 minutes on 2 CPU cores.
# Usage: scripts/generate_reuse_data.sh [OUT_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/reuse}
gen() { .venv/bin/denoiser generate --size 128 --ref-spp 256 --scales 1,2 --quiet --overwrite --out "$OUT" "$@"; }
for seed in 1 2 3; do
  gen --split train --frames 12 --seed "$seed" --scene diffuse_room --scene textured_detail --scene metals \
      --scene fast_camera --scene dark_fireflies --scene swinging_light --scene orbiting_light \
      --scene sliding_over_texture --scene moving_highlights
done
gen --split train --frames 12 --seed 6 --no-jitter --scene diffuse_room --scene textured_detail --scene metals \
    --scene fast_camera --scene dark_fireflies --scene swinging_light --scene orbiting_light \
    --scene sliding_over_texture --scene moving_highlights
gen --split validation --frames 8 --seed 5 --scene diffuse_room --scene orbiting_light
gen --split validation --frames 16 --seed 5 --scene sliding_over_texture --scene moving_highlights --scene textured_detail
gen --split test --frames 16 --seed 4 --scene glass --scene moving_light --scene camera_cut --scene moving_object \
    --scene visible_emitter
