#!/usr/bin/env bash
# Renders two training recipes at 512x512 and builds the multi-resolution dataset of the fine-tunes on resolved
# texture (none shipped; docs/results/findings.md): at 128x128 a checker is finer than a pixel (the reference is its
# pixel average, and the fused kernel learns to blur it), at 512x512 the same checker is resolved and blurring it
# costs detail; a network can only learn the difference from frames of both.
#   data/train512: sliding_over_texture and textured_detail (training recipes; the held-out ones stay held out),
#   seed 1, 12 frames, 128-spp references, 1x only (train split);
#   data/mix512: links to data/reuse-mixed's sequences (scripts/generate_blender_training_data.sh) and to each
#   512x512 sequence four times (a 512x512 sequence gives 16x the crops of a 128x128 one, but a sample reads one
#   sequence: listed once they would be 2 of 54 training sequences, four times 8 of 60).
# About 3 minutes on 2 CPU cores.
# Usage: experiments/generate_512_training_data.sh  (after generate_blender_training_data.sh)
set -euo pipefail
cd "$(dirname "$0")/.."
[ -f data/train512/manifest.json ] || .venv/bin/denoiser generate --size 512 --ref-spp 128 --scales 1 --quiet \
  --out data/train512 --split train --frames 12 --seed 1 --scene sliding_over_texture --scene textured_detail
.venv/bin/python scripts/link_datasets.py data/mix512 reuse-mixed:1:train,validation train512:4:train
