#!/usr/bin/env bash
# Renders the dataset the denoising and upscaling comparisons use (docs/results/denoise_x1.md, upscale_x2.md): whole
# scenes held out of training.
#   train:      diffuse_room, textured_detail, metals, moving_object, fast_camera, dark_fireflies,
#               swinging_light (added for the 2x results: lighting that changes, a recipe unlike moving_light)
#   validation: other seeds of diffuse_room and moving_object
#   test:       glass, moving_light, camera_cut (recipes never seen in training)
# 128x128 render resolution, references at 1x and 2x (256 spp at 256x256: 1024 per 1x pixel).
# About 30 minutes on 2 CPU cores. Usage: scripts/generate_benchmark_data.sh [OUT_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-data/bench}
gen() { .venv/bin/denoiser generate --size 128 --ref-spp 256 --scales 1,2 --quiet --overwrite --out "$OUT" "$@"; }
gen --split train --frames 12 --seed 1 --scene diffuse_room --scene textured_detail --scene metals \
    --scene moving_object --scene fast_camera --scene dark_fireflies
gen --split train --frames 12 --seed 2 --scene textured_detail --scene metals
gen --split train --frames 12 --seed 1 --scene swinging_light
gen --split train --frames 12 --seed 2 --scene swinging_light
gen --split validation --frames 8 --seed 3 --scene diffuse_room --scene moving_object
gen --split test --frames 12 --seed 4 --scene glass --scene moving_light --scene camera_cut
