#!/usr/bin/env bash
# What half a pixel costs (issue 13): a shipped checkpoint evaluated on synthetic test objects with the pixel-centre
# convention it was trained with, and again with pixel centres shifted by half a pixel (`depthnerf eval
# --pixel-center`), paired per object.
#
#   bash scripts/pixel_center_cost.sh [OUT_DIR]        (default: study/pixel_center, git-ignored)
#
# The checkpoints are evaluated on test objects framed as their training data, once with the pixel-centre reading
# they were trained with (data.pixel_center, 0.0 for the shipped ones) and once with `--pixel-center SHIFT` (0.5):
# every image, input and targets, read half a pixel off the reading the model learned. On legacy-framed data
# (integer pixel centres) the trained reading is exact, so this is exactly the error pixelNeRF's (j, i) makes on
# SRN's Blender renders, seen from the other side. Output: OUT_DIR/paired_<checkpoint>.{md,json} (shifted - trained).
#
# Environment: SEED (0: the study's own test objects, never used in training; object k is the same whatever the
# split sizes), OBJECTS (20), STRIDE (25), FRAMING (default: the first checkpoint's training framing, from its
# spec; docs/data.md also reports FRAMING=legacy with the earlier legacy checkpoints), SHIFT (0.5), CHECKPOINTS
# ("cpu-cars-depth cpu-chairs-depth"; their category is the second dash-field).
set -euo pipefail
OUT=${1:-study/pixel_center}
SEED=${SEED:-0}
OBJECTS=${OBJECTS:-20}
STRIDE=${STRIDE:-25}
SHIFT=${SHIFT:-0.5}
CHECKPOINTS=${CHECKPOINTS:-cpu-cars-depth cpu-chairs-depth}
first_ck=${CHECKPOINTS%% *}
FRAMING=${FRAMING:-$(python "$(dirname "$0")/checkpoint_framing.py" "$first_ck")}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
DATA="$OUT/data"

cats=$(for ck in $CHECKPOINTS; do echo "$ck" | cut -d- -f2; done | sort -u)
for cat in $cats; do
  depthnerf synth --category "$cat" --out "$DATA" --train-objects 0 --val-objects 0 --test-objects "$OBJECTS" \
    --resolution 64 --seed "$SEED" --framing "$FRAMING" --quiet
done
for ck in $CHECKPOINTS; do
  cat=$(echo "$ck" | cut -d- -f2)
  depthnerf depth --data "$DATA" --for "$ck" --splits test --category "$cat" --no-progress
  for mode in trained shifted; do
    ev="$OUT/eval/$ck-$mode"
    extra=()
    [ "$mode" = shifted ] && extra=(--pixel-center "$SHIFT")
    [ -f "$ev/summary.json" ] || depthnerf eval --checkpoint "$ck" --data "$DATA" --category "$cat" --split test \
      --views-stride "$STRIDE" --no-mesh "${extra[@]}" --out "$ev" --no-progress
  done
  python "$(dirname "$0")/paired_difference.py" --baseline "$OUT/eval/$ck-trained" --method "$OUT/eval/$ck-shifted" \
    --json "$OUT/paired_$ck.json" | tee "$OUT/paired_$ck.md"
done
