#!/usr/bin/env bash
# Evaluates the shipped fused models on another renderer's frames: Blender Cycles renders of procedural scenes
# that no model was trained on (scripts/render_blender.py; needs bpy, the 'blender' extra), against OIDN and
# OIDN + TAA timed in the same run, at 1x and 2x, with pictures of the last frames.
#   data: orbit (seeds 1, 2), pan (seed 1), 12 frames, and moving_object (seed 3), 16 frames; 128x128, 1 spp,
#   256 spp references at 256x256 (--ref-scale 2: the import keeps them as 2x references and their 2x2 means as the
#   1x ones), all in the test split of DATA, imported with the blender-cycles layout.
#   JITTER=none (the default): the sample at the pixel centre, as Blender renders;
#   JITTER=halton: a TAA jitter per frame (render_blender.py --jitter halton), into renders/blender-x2-jittered,
#   data/blender-eval-jittered and reports named blender_jittered_*.
# Reports: docs/results/blender[_jittered]_x{1,2}.{json,md};
# pictures docs/blender[_jittered]_{orbit,moving_object}_x{1,2}.png.
# About 25 minutes on 2 CPU cores (rendering 15, each evaluation about 3).
# Usage: scripts/reproduce_blender_results.sh   (JITTER=none|halton RENDERS=... DATA=...)
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh --blender  # the project and bpy (the 'blender' extra), idempotent
JITTER=${JITTER:-none}
case "$JITTER" in
  none) name=blender; suffix= ;;
  halton) name=blender_jittered; suffix=-jittered ;;
  *) echo "JITTER must be none or halton, not '$JITTER'" >&2; exit 2 ;;
esac
RENDERS=${RENDERS:-renders/blender-x2$suffix}
DATA=${DATA:-data/blender-eval$suffix}

render() {  # NAME SCENE FRAMES SEED
  local last
  last=$(printf '%s/%s/references/frame_%04d.exr' "$RENDERS" "$1" $(($3 - 1)))
  [ -f "$last" ] || .venv/bin/python scripts/render_blender.py --out "$RENDERS/$1" --scene "$2" --frames "$3" \
    --seed "$4" --size 128 --ref-spp 256 --ref-scale 2 --jitter "$JITTER" > "$RENDERS-$1.log" 2>&1
  .venv/bin/denoiser import --layout blender-cycles "$RENDERS/$1" --out "$DATA" --split test --overwrite > /dev/null
}
mkdir -p "$RENDERS" docs/results var/results
render orbit_s1 orbit 12 1
render pan_s1 pan 12 1
render orbit_s2 orbit 12 2
render moving_object_s3 moving_object 16 3

for scale in 1 2; do
  if [ "$scale" = 1 ]; then ours=(--method fused-balanced-x1 --method fused-fast-x1 --method fused-high-x1); else ours=(--method fused-balanced-x2 --method fused-fast-x2); fi
  .venv/bin/denoiser evaluate --data "$DATA" --split test --scale "$scale" --threads 2 "${ours[@]}" \
    --method oidn-taa:fast --method oidn-taa:balanced --method oidn-taa:high --method oidn:fast \
    --method oidn:balanced --method oidn:high --out "docs/results/${name}_x$scale.json" \
    | tee "docs/results/${name}_x$scale.md"
done
picture() {  # SEQUENCE SCALE ZOOM MODEL OUT
  .venv/bin/denoiser compare --data "$DATA" --sequence "$1" --frame -1 --scale "$2" --zoom "$3" \
    --method oidn:high=OIDN-high --method oidn-taa:balanced=OIDN+TAA-balanced --method "$4=$4" --out "$5"
}
picture orbit_s2 1 40,40,48 fused-balanced-x1 docs/${name}_orbit_x1.png
picture moving_object_s3 1 40,40,48 fused-balanced-x1 docs/${name}_moving_object_x1.png
picture orbit_s2 2 80,80,96 fused-balanced-x2 docs/${name}_orbit_x2.png
picture moving_object_s3 2 80,80,96 fused-balanced-x2 docs/${name}_moving_object_x2.png
