#!/usr/bin/env bash
# Reproduces the right-sizing result (docs/fit.md): `denoiser fit` picks a smaller WSKPN preset for a simple scene
# (diffuse, static light) than for a hard one (glossy metal, changing light), with the same quality target.
# The two datasets hold the same sequences (same seeds, so the same frames) as these of
# scripts/generate_benchmark_data.sh:
#   simple: train diffuse_room_s1, validation diffuse_room_s3
#   hard:   train metals_s1 + swinging_light_s1, validation metals_s2 + swinging_light_s2
# Rendering about 3 minutes, the two fits about 5 minutes on 2 CPU cores. Ladders (JSON + Markdown) are
# written to docs/results/fit/{simple,hard}/ladder.{json,md} for the default target psnr=29.5, and to
# ladder-TARGET.{json,md} for another (e.g. `within=0.2` -> ladder-within-0.2.md); presets already trained with
# the same settings are reused. Usage: scripts/reproduce_fit_results.sh [TARGET]
set -euo pipefail
cd "$(dirname "$0")/.."
TARGET=${1:-psnr=29.5}
STEPS=${FIT_STEPS:-300}
gen() { .venv/bin/denoiser generate --size 128 --ref-spp 256 --scales 1,2 --quiet "$@"; }
simple=(--scene diffuse_room)
hard=(--scene metals --scene swinging_light)
[ -d data/fit-simple/diffuse_room_s1 ] || gen --out data/fit-simple --split train --frames 12 --seed 1 "${simple[@]}"
[ -d data/fit-simple/diffuse_room_s3 ] || gen --out data/fit-simple --split validation --frames 8 --seed 3 "${simple[@]}"
[ -d data/fit-hard/metals_s1 ] || gen --out data/fit-hard --split train --frames 12 --seed 1 "${hard[@]}"
[ -d data/fit-hard/metals_s2 ] || gen --out data/fit-hard --split validation --frames 12 --seed 2 "${hard[@]}"
suffix=""
[ "$TARGET" = "psnr=29.5" ] || suffix="-${TARGET//=/-}"
for kind in simple hard; do
  mkdir -p "docs/results/fit/$kind" "var/results/fit/$kind"
  status=0
  .venv/bin/denoiser fit --data "data/fit-$kind" --method wskpn --presets xs,s,m,l --target "$TARGET" \
    --steps "$STEPS" --crop 48 --threads 1 --time-at 128x128 --no-tracking --out "runs/fit-$kind" \
    --json "var/results/fit/$kind/ladder$suffix.json" || status=$?
  # Exit 1 means no preset met the target: the ladder is still written and worth reading.
  [ "$status" = 0 ] || [ "$status" = 1 ] || exit "$status"
  cp "runs/fit-$kind/ladder.md" "docs/results/fit/$kind/ladder$suffix.md"
done
