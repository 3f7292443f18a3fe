#!/usr/bin/env bash
# Reproduces the reuse results (docs/results/reuse_*): the fused family (OIDN + learned temporal reuse) trained on
# the dataset of scripts/generate_reuse_data.sh (rendered first if missing), then evaluated on its held-out test
# recipes at 1x and 2x against OIDN (fast, balanced, high) and OIDN + TAA at the same qualities, timed in the same
# run, with side-by-side pictures of the moving-light and moving-object cases; then it ships the default
# preset at both scales, the fast preset at both and the high one at 1x as the repository's pretrained models
# (pretrained/fused-{balanced,fast}-x{1,2}, fused-high-x1: weights, recipe and the held-out rows of these reports;
# scripts/ship_pretrained.py); the three 1x models are shipped running the fused blend before the kernel as history
# (trained with the filtered output as history, as every model is) and without their kernel on frames above 32768
# pixels, the 2x models as trained.
# On the 2-core CPU, one torch thread per training run: fused:balanced at 1x and at 2x side by side (13 and
# 25 minutes), then 600 steps with longer histories at 1x beside the fast preset fine-tuned from the 2x model, then
# 3100 steps with the display-error term at 1x (about 18 minutes), then the fast / high presets at 1x fine-tuned
# from that model, then 600 steps with the term for each 2x model (about 8 minutes side by side), then fine-tunes
# with the normals' world frame randomly rotated (training's augment; the stages before were trained without it and
# without the dataset's jitter-free sequences, which reproducing them now includes): 1500 steps at 1x beside 1000 at
# 2x, then 1000 more at 2x and 1000 for the fast 2x model, and the 1x fast / high presets again (about 30 minutes).
# Checkpoints of the rotation fine-tunes were chosen by validation on both renderers: data/reuse's validation
# split and Blender's orbit_s1 and pan_s1 (scripts/reproduce_blender_results.sh).
# Last, at 1x, on Mitsuba and Blender Cycles frames together (needs bpy): 1500 steps, then the network grown by the
# clipped running mean of OIDN's estimates, and the fast / high presets from it (about 25 minutes); then both 2x
# models grown the same way (1000 steps each, about 20 minutes), then fine-tuned on the mixed frames (600 steps each,
# about 25 minutes).
# Usage: scripts/reproduce_reuse_results.sh [DATA_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-data/reuse}
STEPS_X1=${STEPS_X1:-2000}
STEPS_X2=${STEPS_X2:-1500}
[ -f "$DATA/manifest.json" ] || bash scripts/generate_reuse_data.sh "$DATA"
# The first stage trains without the run-time settings (--no-shipped-settings): they were measured on its weights
# and its fine-tunes, each added later, and the stages below set them where the shipped models took them.
train=(.venv/bin/denoiser train --data "$DATA" --method fused:balanced --frames-per-sample 10 --batch 4
       --lr 2e-3 --threads 1 --validate-every 250 --checkpoint-every 250 --quiet --no-shipped-settings)
"${train[@]}" --scale 1 --crop 64 --steps "$STEPS_X1" --out runs/fused-balanced-x1 > runs-fused-balanced-x1.log 2>&1 &
"${train[@]}" --scale 2 --crop 48 --steps "$STEPS_X2" --out runs/fused-balanced-x2 > runs-fused-balanced-x2.log 2>&1 &
wait
# Then longer histories at 1x (12 frames per sample, the whole training sequence), and the two other OIDN qualities
# fine-tuned from it (the network is the same; it adapts to the other preset's OIDN output).
tune=(.venv/bin/denoiser train --data "$DATA" --frames-per-sample 12 --batch 4 --lr 5e-4 --warmup 10 --threads 1
      --crop 64 --quiet --scale 1)
"${tune[@]}" --method fused:balanced --init-from runs/fused-balanced-x1/best.pt --steps 600 --validate-every 150 \
  --checkpoint-every 150 --out runs/fused-balanced-x1-long > runs-fused-balanced-x1-long.log 2>&1 &
# At 2x the fast preset (OIDN-fast inside) is the one that can run within OIDN-high's time at 128x128.
.venv/bin/denoiser train --data "$DATA" --frames-per-sample 10 --batch 4 --lr 5e-4 --warmup 10 --threads 1 --crop 48 \
  --quiet --scale 2 --method fused:fast --init-from runs/fused-balanced-x2/best.pt --steps 200 --validate-every 100 \
  --checkpoint-every 100 --out runs/fused-fast-x2 > runs-fused-fast-x2.log 2>&1 &
wait
# Then the display-error term (display_weight 50: squared error on display-encoded images, what PSNR measures) in
# three fine-tunes of 600, 1000 and 1500 steps, each from the last's best checkpoint (each stage gained on
# validation; 600 steps without the term gained nothing).
previous=runs/fused-balanced-x1-long/best.pt
for stage in 600:150 1000:200 1500:250; do  # steps:validation interval
  steps=${stage%:*} every=${stage#*:}
  "${tune[@]}" --method fused:balanced --init-from "$previous" --steps "$steps" --display-weight 50 \
    --validate-every "$every" --checkpoint-every "$every" --out "runs/fused-balanced-x1-display-$steps" \
    > "runs-fused-balanced-x1-display-$steps.log" 2>&1
  previous="runs/fused-balanced-x1-display-$steps/best.pt"
done
for quality in fast high; do
  "${tune[@]}" --method "fused:$quality" --init-from "$previous" --steps 200 --display-weight 50 \
    --validate-every 100 --checkpoint-every 100 --out "runs/fused-$quality-x1" > "runs-fused-$quality-x1.log" 2>&1 &
done
wait
# The display-error term at 2x too: 600 steps of each 2x model, side by side.
for preset in balanced fast; do
  .venv/bin/denoiser train --data "$DATA" --frames-per-sample 10 --batch 4 --lr 5e-4 --warmup 10 --threads 1 \
    --crop 48 --quiet --scale 2 --method "fused:$preset" --init-from "runs/fused-$preset-x2/best.pt" --steps 600 \
    --validate-every 150 --checkpoint-every 150 --display-weight 50 --out "runs/fused-$preset-x2-display" \
    > "runs-fused-$preset-x2-display.log" 2>&1 &
done
wait
# The normals' world frame rotated at random per sample (what the augment option does now), with the display-error
# term: a fine-tune of each model. Two stages at 1x were run: the second gained on this validation split and lost
# on Blender's validation sequences, so the first is kept (a model for every renderer) and fine-tuned on both
# renderers' frames below. At 2x the second balanced stage is shipped (better on both); a second fast stage (worse
# on Blender's) was not.
rot=(.venv/bin/denoiser train --data "$DATA" --batch 4 --lr 5e-4 --warmup 10 --threads 1 --quiet --display-weight 50)
"${rot[@]}" --scale 1 --crop 64 --frames-per-sample 12 --method fused:balanced \
  --init-from runs/fused-balanced-x1-display-1500/best.pt --steps 1500 --validate-every 250 --checkpoint-every 250 \
  --out runs/fused-balanced-x1-rot > runs-fused-balanced-x1-rot.log 2>&1 &
"${rot[@]}" --scale 2 --crop 48 --frames-per-sample 10 --method fused:balanced \
  --init-from runs/fused-balanced-x2-display/best.pt --steps 1000 --validate-every 250 --checkpoint-every 250 \
  --out runs/fused-balanced-x2-rot > runs-fused-balanced-x2-rot.log 2>&1 &
wait
"${rot[@]}" --scale 2 --crop 48 --frames-per-sample 10 --method fused:fast --init-from runs/fused-fast-x2-display/best.pt \
  --steps 1000 --validate-every 250 --checkpoint-every 250 --out runs/fused-fast-x2-rot > runs-fused-fast-x2-rot.log 2>&1 &
for quality in fast high; do
  "${rot[@]}" --scale 1 --crop 64 --frames-per-sample 12 --method "fused:$quality" \
    --init-from runs/fused-balanced-x1-rot/best.pt --steps 200 --validate-every 100 --checkpoint-every 100 \
    --out "runs/fused-$quality-x1-rot" > "runs-fused-$quality-x1-rot.log" 2>&1
done
wait
"${rot[@]}" --scale 2 --crop 48 --frames-per-sample 10 --method fused:balanced \
  --init-from runs/fused-balanced-x2-rot/best.pt --steps 1000 --validate-every 250 --checkpoint-every 250 \
  --out runs/fused-balanced-x2-rot2 > runs-fused-balanced-x2-rot2.log 2>&1
# Then the 1x model fine-tuned on Mitsuba and Blender Cycles frames together (scripts/generate_blender_training_data.sh,
# needs bpy): 1500 steps from the rotation fine-tune, the checkpoint of step 1250 (better on Blender's orbit_s1 /
# pan_s1 than before); the fast / high presets 200 steps from it.
bash scripts/generate_blender_training_data.sh
mixed=(.venv/bin/denoiser train --data data/reuse-mixed --batch 4 --lr 5e-4 --warmup 10 --threads 1 --quiet
       --display-weight 50 --scale 1 --crop 64 --frames-per-sample 12)
"${mixed[@]}" --method fused:balanced --init-from runs/fused-balanced-x1-rot/best.pt --steps 1500 --validate-every 250 \
  --checkpoint-every 250 --out runs/fused-balanced-x1-mixed > runs-fused-balanced-x1-mixed.log 2>&1
# Then the network with the clipped running mean of OIDN's estimates as a fourth candidate (model/methods/fused.py;
# --init-from the three-candidate model grows it with the new weights at zero), on the same data at a lower
# learning rate (2e-4, another seed's crops), a 2500-step schedule stopped at step 1250 for time; the fast / high
# presets 600 steps from it (best validation: fast step 600, high step 400), shipped as fused-fast-x1 and
# fused-high-x1. The same run without the new candidate scored lower; the plain mean as a fifth candidate ghosted
# more.
"${mixed[@]}" --method fused:balanced --init-from runs/fused-balanced-x1-mixed/best.pt --lr 2e-4 --seed 2 --steps 2500 \
  --validate-every 250 --checkpoint-every 250 --out runs/fused-balanced-x1-cmean > runs-fused-balanced-x1-cmean.log 2>&1
for quality in fast high; do
  "${mixed[@]}" --method "fused:$quality" --init-from runs/fused-balanced-x1-cmean/best.pt --steps 600 \
    --validate-every 100 --checkpoint-every 100 --out "runs/fused-$quality-x1-cmean" > "runs-fused-$quality-x1-cmean.log" 2>&1 &
done
wait
# The 2x models grown the same way (the clipped running mean as a fourth candidate, --init-from the three-candidate
# model), 1000 steps each on data/reuse at lr 2e-4, another seed's crops, side by side (about 20 minutes):
# both gained on validation, the last checkpoint the best of both.
x2tune=(.venv/bin/denoiser train --data "$DATA" --batch 4 --lr 2e-4 --warmup 10 --threads 1 --quiet --display-weight 50
        --scale 2 --crop 48 --frames-per-sample 10 --seed 2 --steps 1000 --validate-every 250 --checkpoint-every 250)
"${x2tune[@]}" --method fused:balanced --init-from runs/fused-balanced-x2-rot2/best.pt \
  --out runs/fused-balanced-x2-cmean > runs-fused-balanced-x2-cmean.log 2>&1 &
"${x2tune[@]}" --method fused:fast --init-from runs/fused-fast-x2-rot/best.pt \
  --out runs/fused-fast-x2-cmean > runs-fused-fast-x2-cmean.log 2>&1 &
wait
# Then both 2x models fine-tuned on Mitsuba and Blender Cycles frames together, as the 1x model was
# (data/reuse-mixed: its Blender sequences carry 2x references), 600 steps each at lr 5e-4, side by side.
x2mixed=(.venv/bin/denoiser train --data data/reuse-mixed --batch 4 --lr 5e-4 --warmup 10 --threads 1 --quiet
         --display-weight 50 --scale 2 --crop 48 --frames-per-sample 10 --seed 3 --steps 600 --validate-every 150
         --checkpoint-every 150)
for preset in balanced fast; do
  "${x2mixed[@]}" --method "fused:$preset" --init-from "runs/fused-$preset-x2-cmean/best.pt" \
    --out "runs/fused-$preset-x2-mixed" > "runs-fused-$preset-x2-mixed.log" 2>&1 &
done
wait
mkdir -p docs/results var/results
peers=(--method oidn-taa:fast --method oidn-taa:balanced --method oidn-taa:high --method oidn:fast
       --method oidn:balanced --method oidn:high --method accumulation --method accumulation:rectified --method svgf
       --method svgf:rectified)
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 2 --threads 2 \
  --method runs/fused-balanced-x2-mixed/best.pt --method runs/fused-fast-x2-mixed/best.pt "${peers[@]}" \
  --out var/results/reuse_x2.json | tee docs/results/reuse_x2.md
# The hard frames, side by side: input, OIDN-high, OIDN + TAA, ours, reference.
picture() {  # SEQUENCE FRAME SCALE ZOOM OUT CHECKPOINT
  .venv/bin/denoiser compare --data "$DATA" --sequence "$1" --frame "$2" --scale "$3" --zoom "$4" \
    --method oidn:high=OIDN-high --method oidn-taa:balanced=OIDN+TAA-balanced \
    --method "$6=fused-balanced" --out "$5"
}
x1=runs/fused-balanced-x1-cmean/best.pt
x2=runs/fused-balanced-x2-mixed/best.pt
picture visible_emitter_s4 10 2 80,60,112 docs/reuse_visible_emitter_x2.png "$x2"
picture moving_object_s4 -1 2 60,80,112 docs/reuse_moving_object_x2.png "$x2"
# The default preset at both scales as the repository's pretrained models (1x: the longer-history fine-tune, its
# first stage recorded too; the 1x models' held-out rows come from the evaluation at the end).
ship=(.venv/bin/python scripts/ship_pretrained.py --data "$DATA" --dataset-script scripts/generate_reuse_data.sh
      --training-script scripts/reproduce_reuse_results.sh)
"${ship[@]}" "$x1" --name fused-balanced-x1 --stage runs/fused-balanced-x1/best.pt \
  --stage runs/fused-balanced-x1-long/best.pt --stage runs/fused-balanced-x1-display-600/best.pt \
  --stage runs/fused-balanced-x1-display-1000/best.pt --stage runs/fused-balanced-x1-display-1500/best.pt \
  --stage runs/fused-balanced-x1-rot/best.pt --stage runs/fused-balanced-x1-mixed/best.pt
"${ship[@]}" "$x2" --name fused-balanced-x2 --data data/reuse-mixed \
  --dataset-script scripts/generate_blender_training_data.sh --stage runs/fused-balanced-x2/best.pt \
  --stage runs/fused-balanced-x2-display/best.pt --stage runs/fused-balanced-x2-rot/best.pt \
  --stage runs/fused-balanced-x2-rot2/best.pt --stage runs/fused-balanced-x2-cmean/best.pt \
  --report var/results/reuse_x2.json
# The 1x fast and high presets, fine-tuned from the 1x model above on the mixed data (its stages are theirs too).
for quality in fast high; do
  "${ship[@]}" "runs/fused-$quality-x1-cmean/best.pt" --name "fused-$quality-x1" --data data/reuse-mixed \
    --dataset-script scripts/generate_blender_training_data.sh --stage runs/fused-balanced-x1/best.pt \
    --stage runs/fused-balanced-x1-long/best.pt --stage runs/fused-balanced-x1-display-600/best.pt \
    --stage runs/fused-balanced-x1-display-1000/best.pt --stage runs/fused-balanced-x1-display-1500/best.pt \
    --stage runs/fused-balanced-x1-rot/best.pt --stage runs/fused-balanced-x1-mixed/best.pt --stage "$x1"
done
"${ship[@]}" runs/fused-fast-x2-mixed/best.pt --name fused-fast-x2 --data data/reuse-mixed \
  --dataset-script scripts/generate_blender_training_data.sh --stage runs/fused-balanced-x2/best.pt \
  --stage runs/fused-fast-x2/best.pt --stage runs/fused-fast-x2-display/best.pt --stage runs/fused-fast-x2-rot/best.pt \
  --stage runs/fused-fast-x2-cmean/best.pt --report var/results/reuse_x2.json
# Last, the three 1x models re-shipped running the fused blend before the kernel as the next frame's history (the
# same weights), evaluated at 1x beside the checkpoints as trained (the
# filtered output as history), and their manifests' held-out rows taken from that run; the 1x pictures with them.
# They also skip their output kernel on frames of more than 32768 render pixels (twice the 128x128 they were trained
# on): the same outputs at 128x128, the fused blend above.
reship() {  # "SETTING FLAGS" NAME...: each shipped model shipped again with those run-time settings, weights unchanged
  local settings=$1 name
  shift
  for name in "$@"; do
    # shellcheck disable=SC2086  # the settings are flags to split
    .venv/bin/python scripts/ship_pretrained.py "pretrained/$name/model.pt" --name "$name" --after-shipped "$name" \
      $settings
  done
}
reship "--history-before-kernel --kernel-max-pixels 32768" fused-balanced-x1 fused-fast-x1 fused-high-x1
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 --method fused-balanced-x1 \
  --method fused-fast-x1 --method fused-high-x1 --method "$x1" --method runs/fused-fast-x1-cmean/best.pt \
  --method runs/fused-high-x1-cmean/best.pt "${peers[@]}" --out var/results/reuse_x1.json | tee docs/results/reuse_x1.md
remeasure() {  # REPORT NAME...: each shipped model takes its held-out rows from REPORT, weights unchanged
  local report=$1 name
  shift
  for name in "$@"; do
    .venv/bin/python scripts/ship_pretrained.py "pretrained/$name/model.pt" --name "$name" --remeasure \
      --report "$report" --report-source "pretrained:$name"
  done
}
remeasure var/results/reuse_x1.json fused-balanced-x1 fused-fast-x1 fused-high-x1
picture visible_emitter_s4 10 1 40,30,56 docs/reuse_visible_emitter_x1.png fused-balanced-x1
picture moving_object_s4 -1 1 30,40,56 docs/reuse_moving_object_x1.png fused-balanced-x1
# The moving light with the high preset too (the one at or above OIDN-high on every sequence).
.venv/bin/denoiser compare --data "$DATA" --sequence moving_light_s4 --frame -1 --scale 1 --zoom 30,50,56 \
  --method oidn:high=OIDN-high --method oidn-taa:balanced=OIDN+TAA-balanced --method fused-balanced-x1=fused-balanced \
  --method fused-high-x1=fused-high --out docs/reuse_moving_light_x1.png
# Later stages, each measured on its own (docs/results/findings.md), the weights unchanged: the running mean's
# 8-frame window at both scales, and the stale-history test at 1x.
reship "--mean-max-frames 8 --stale-test-sigmas 2" fused-balanced-x1 fused-fast-x1 fused-high-x1
reship "--mean-max-frames 8" fused-balanced-x2 fused-fast-x2
# The default model trained with its sample mean: 400 steps from the
# shipped weights with sample_mean_frames 8; the best validation checkpoint ships.
.venv/bin/python -c "from model.deployment.pretrained import load_pretrained; from model.training.checkpoint import save_checkpoint
m = load_pretrained('fused-balanced-x1'); m.set_sample_mean_frames(8); save_checkpoint('runs/balanced-sm8-init.pt', method=m)"
.venv/bin/denoiser train --data "$DATA" --method fused:balanced --init-from runs/balanced-sm8-init.pt --batch 4 \
  --lr 2e-4 --warmup 10 --threads 1 --quiet --display-weight 50 --scale 1 --crop 64 --frames-per-sample 12 --seed 5 \
  --steps 400 --validate-every 100 --checkpoint-every 100 --no-tracking --out runs/sm8-balanced
cp runs/sm8-balanced/best.pt runs/sm8-balanced-best.pt
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 --method runs/sm8-balanced-best.pt \
  --method fused-fast-x1 --method fused-high-x1 "${peers[@]}" --out var/results/reuse_x1_sample_mean.json
.venv/bin/python scripts/ship_pretrained.py runs/sm8-balanced-best.pt --name fused-balanced-x1 \
  --after-shipped fused-balanced-x1 --data "$DATA" --dataset-script scripts/generate_reuse_data.sh \
  --report var/results/reuse_x1_sample_mean.json
# The fast preset with the sample mean, its weights unchanged, once the mean averages OIDN's guides too.
.venv/bin/python -c "from model.deployment.pretrained import load_pretrained; from model.training.checkpoint import save_checkpoint
m = load_pretrained('fused-fast-x1'); m.set_sample_mean_frames(8); save_checkpoint('runs/fast-sm8.pt', method=m)"
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 --method fused-balanced-x1 \
  --method runs/fast-sm8.pt --method fused-fast-x1 --method fused-high-x1 "${peers[@]}" \
  --out var/results/reuse_x1_guides_mean.json
.venv/bin/python scripts/ship_pretrained.py pretrained/fused-fast-x1/model.pt --name fused-fast-x1 \
  --after-shipped fused-fast-x1 --sample-mean-frames 8 --report var/results/reuse_x1_guides_mean.json \
  --report-source runs/fast-sm8.pt
# The high preset with the sample mean, its weights unchanged, keeping the mean's frames in the network's history
# share cubed; one quiet run of the shipped 1x models and the peers.
.venv/bin/python -c "from model.deployment.pretrained import load_pretrained; from model.training.checkpoint import save_checkpoint
m = load_pretrained('fused-high-x1'); m.set_sample_mean_frames(8); m.set_sample_mean_trust_power(3.0)
save_checkpoint('runs/high-sm8-p3.pt', method=m)"
reship "--sample-mean-frames 8 --sample-mean-trust-power 3" fused-high-x1
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 --method fused-balanced-x1 \
  --method fused-fast-x1 --method fused-high-x1 "${peers[@]:0:12}" --out var/results/reuse_x1_mean_trust.json \
  | tee docs/results/reuse_x1_mean_trust.md
remeasure var/results/reuse_x1_mean_trust.json fused-balanced-x1 fused-fast-x1 fused-high-x1
# The 2x models with the sample mean, their weights unchanged; one run with the peers.
reship "--sample-mean-frames 8" fused-balanced-x2 fused-fast-x2
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 2 --threads 2 --method fused-balanced-x2 \
  --method fused-fast-x2 "${peers[@]:0:12}" --out var/results/reuse_x2_sample_mean.json \
  | tee docs/results/reuse_x2_sample_mean.md
remeasure var/results/reuse_x2_sample_mean.json fused-balanced-x2 fused-fast-x2
# Every fused model with a looser stale-history test, weights unchanged: 0.5 standard errors at 1x, and the test
# switched on at 2x at 1; one run each with the peers.
reship "--stale-test-sigmas 0.5" fused-balanced-x1 fused-fast-x1 fused-high-x1
reship "--stale-test-sigmas 1" fused-balanced-x2 fused-fast-x2
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 --method fused-balanced-x1 \
  --method fused-fast-x1 --method fused-high-x1 "${peers[@]:0:12}" --out var/results/reuse_x1_stale_low.json \
  | tee docs/results/reuse_x1_stale_low.md
remeasure var/results/reuse_x1_stale_low.json fused-balanced-x1 fused-fast-x1 fused-high-x1
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 2 --threads 2 --method fused-balanced-x2 \
  --method fused-fast-x2 "${peers[@]:0:12}" --out var/results/reuse_x2_stale_low.json \
  | tee docs/results/reuse_x2_stale_low.md
remeasure var/results/reuse_x2_stale_low.json fused-balanced-x2 fused-fast-x2
# Every fused model with the regional stale-history test over 33 x 33 render pixels, weights unchanged; one run each
# with the models before it (copied first) and the peers.
mkdir -p runs/old
for name in fused-balanced-x1 fused-fast-x1 fused-high-x1 fused-balanced-x2 fused-fast-x2; do
  cp "pretrained/$name/model.pt" "runs/old/$name.pt"
done
reship "--stale-region-pixels 33" fused-balanced-x1 fused-fast-x1 fused-high-x1 fused-balanced-x2 fused-fast-x2
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 --method fused-balanced-x1 \
  --method fused-fast-x1 --method fused-high-x1 --method runs/old/fused-balanced-x1.pt \
  --method runs/old/fused-fast-x1.pt --method runs/old/fused-high-x1.pt "${peers[@]:0:12}" \
  --out var/results/reuse_x1_stale_region.json | tee docs/results/reuse_x1_stale_region.md
remeasure var/results/reuse_x1_stale_region.json fused-balanced-x1 fused-fast-x1 fused-high-x1
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 2 --threads 2 --method fused-balanced-x2 \
  --method fused-fast-x2 --method runs/old/fused-balanced-x2.pt --method runs/old/fused-fast-x2.pt \
  "${peers[@]:0:12}" --out var/results/reuse_x2_stale_region.json | tee docs/results/reuse_x2_stale_region.md
remeasure var/results/reuse_x2_stale_region.json fused-balanced-x2 fused-fast-x2
# The same weights and settings after the box means and the jitter resample got faster: one run per scale with the
# peers, every shipped fused model remeasured from it.
measure() {  # NAME SCALE MODEL...: one held-out run of the models and the peers, the models remeasured from it
  local report=docs/results/$1.json scale=$2 name models=()
  shift 2
  for name in "$@"; do models+=(--method "$name"); done
  .venv/bin/denoiser evaluate --data "$DATA" --split test --scale "$scale" --threads 2 "${models[@]}" \
    "${peers[@]:0:12}" --out "$report" | tee "${report%.json}.md"
  remeasure "$report" "$@"
}
measure reuse_x1_fast_ops 1 fused-balanced-x1 fused-fast-x1 fused-high-x1
measure reuse_x2_fast_ops 2 fused-balanced-x2 fused-fast-x2
# The default 1x model fine-tuned on Mitsuba and Blender Cycles frames together again: its sample-mean stage above
# read data/reuse alone, and on Cycles' frames with a TAA jitter it fell behind the fast preset, whose last stage
# read the mixed data. 600 steps from the shipped weights
# and settings at the fast / high presets' rate (5e-4), the best validation checkpoint (step 500) shipped; one
# held-out run beside the model before it (copied first) and the peers. Its Blender numbers come from
# scripts/reproduce_blender_results.sh (JITTER=none and JITTER=halton).
cp pretrained/fused-balanced-x1/model.pt runs/old/fused-balanced-x1.pt
"${mixed[@]}" --method fused:balanced --init-from fused-balanced-x1 --seed 0 --steps 600 --validate-every 100 \
  --checkpoint-every 100 --no-tracking --out runs/balanced-mixed-lr5 > runs-balanced-mixed-lr5.log 2>&1
cp runs/balanced-mixed-lr5/best.pt runs/balanced-mixed-lr5-best.pt
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 --method runs/balanced-mixed-lr5-best.pt \
  --method fused-fast-x1 --method fused-high-x1 --method runs/old/fused-balanced-x1.pt "${peers[@]:0:12}" \
  --out var/results/reuse_x1_mixed_balanced.json | tee docs/results/reuse_x1_mixed_balanced.md
.venv/bin/python scripts/ship_pretrained.py runs/balanced-mixed-lr5-best.pt --name fused-balanced-x1 \
  --after-shipped fused-balanced-x1 --data data/reuse-mixed --dataset-script scripts/generate_blender_training_data.sh \
  --training-script scripts/reproduce_reuse_results.sh --report var/results/reuse_x1_mixed_balanced.json
# The 1x models reading OIDN's estimate at the pixel centres: the same
# weights, shipped with --unjitter-estimate first into a scratch folder (runs/unjitter/NAME.pt), evaluated beside the
# models before (copied to runs/old/) and the peers in one run, then shipped with that run's numbers; and the peers
# with the same read, for what it alone is worth (experiments/measure_unjittered_peers.py).
mkdir -p runs/unjitter
rm -rf runs/unjitter/pretrained && cp -r pretrained runs/unjitter/pretrained
for name in fused-balanced-x1 fused-fast-x1 fused-high-x1; do
  cp "pretrained/$name/model.pt" "runs/old/$name.pt"
  .venv/bin/python scripts/ship_pretrained.py "pretrained/$name/model.pt" --name "$name" --after-shipped "$name" \
    --unjitter-estimate --root runs/unjitter/pretrained
  cp "runs/unjitter/pretrained/$name/model.pt" "runs/unjitter/$name.pt"
done
.venv/bin/denoiser evaluate --data "$DATA" --split test --scale 1 --threads 2 \
  --method runs/unjitter/fused-balanced-x1.pt --method runs/unjitter/fused-fast-x1.pt \
  --method runs/unjitter/fused-high-x1.pt --method runs/old/fused-balanced-x1.pt --method runs/old/fused-fast-x1.pt \
  --method runs/old/fused-high-x1.pt "${peers[@]:0:12}" --out var/results/reuse_x1_unjittered.json \
  | tee docs/results/reuse_x1_unjittered.md
for name in fused-balanced-x1 fused-fast-x1 fused-high-x1; do
  .venv/bin/python scripts/ship_pretrained.py "pretrained/$name/model.pt" --name "$name" --after-shipped "$name" \
    --unjitter-estimate --report var/results/reuse_x1_unjittered.json --report-source "runs/unjitter/$name.pt"
done
.venv/bin/python experiments/measure_unjittered_peers.py --data "$DATA" --split test \
  --out var/results/reuse_x1_unjittered_peers.json
