#!/usr/bin/env bash
# The foreground-opacity term (--schedule.foreground_opacity_weight; docs/RESULTS.md, "A foreground-opacity
# term") on a shipped model: its weights continued for STEPS steps with the annealing recipe
# (scripts/anneal_recipe.sh) twice, side by side, one thread each: once as they are (the control) and once with the
# term at WEIGHT. Both runs and the shipped model are scored on the study's 50 test objects (renders and meshes
# saved), paired per object against the control, with the chairs' leg band (scripts/leg_geometry.py). Resumable:
# every stage skips finished work.
#
#   bash scripts/foreground_study.sh DIR                              # chairs, cpu-chairs-sym-pp, weight 0.05
#   WEIGHT=0.2 STEPS=3000 bash scripts/foreground_study.sh DIR
#   STEPS=4 TRAIN=3 VAL=1 TEST=2 bash scripts/foreground_study.sh /tmp/f   # a smoke run of the script
set -euo pipefail
OUT=$1
CATEGORY=${CATEGORY:-chairs}
CHECKPOINT=${CHECKPOINT:-cpu-$CATEGORY-sym-pp}
STEPS=${STEPS:-2000}
WEIGHT=${WEIGHT:-0.05}
TRAIN=${TRAIN:-300}
VAL=${VAL:-20}
TEST=${TEST:-50}
SEED=${SEED:-4}
HERE=$(cd "$(dirname "$0")" && pwd)
source "$HERE/anneal_recipe.sh"
mkdir -p "$OUT"
export OMP_NUM_THREADS=1

[ -f "$OUT/data/${CATEGORY}_card.json" ] || depthnerf synth --category "$CATEGORY" --out "$OUT/data" \
  --train-objects "$TRAIN" --val-objects "$VAL" --test-objects "$TEST" --resolution 64 --seed 0 --framing srn \
  --workers 2 --quiet
depthnerf depth --data "$OUT/data" --for "$CHECKPOINT" --no-progress

anneal_flags "$CHECKPOINT"
train() {  # train() NAME WEIGHT
  local run="$OUT/runs/$1"
  [ -d "$run/checkpoints/step_$(printf %08d "$STEPS")" ] || depthnerf train --preset "cpu-$CATEGORY" \
    --data "$OUT/data" --depth bundled --depth-checkpoint srn --model.mirror true --model.prior_at_point true \
    --seed "$SEED" "${ANNEAL_FLAGS[@]}" --schedule.foreground_opacity_weight "$2" --max-steps "$STEPS" \
    --checkpoint-every 250 --out "$run" --resume --no-progress > "$OUT/train_$1.log" 2>&1
}
train control 0 &
train "fg$WEIGHT" "$WEIGHT" &
wait

score() {  # score() CHECKPOINT NAME
  [ -f "$OUT/eval/$2/summary.json" ] || depthnerf eval --checkpoint "$1" --data "$OUT/data" --split test \
    --views-stride 25 --save-renders --out "$OUT/eval/$2" --no-progress > "$OUT/eval_$2.log" 2>&1
}
score "$OUT/runs/control" control &
score "$OUT/runs/fg$WEIGHT" "fg$WEIGHT" &
wait
score "$CHECKPOINT" shipped
python "$HERE/paired_difference.py" --baseline "$OUT/eval/control" --method "$OUT/eval/fg$WEIGHT" \
  | tee "$OUT/paired.md"
python "$HERE/paired_difference.py" --baseline "$OUT/eval/shipped" --method "$OUT/eval/control" \
  "$OUT/eval/fg$WEIGHT" | tee "$OUT/paired_shipped.md"
[ "$CATEGORY" != chairs ] || python "$HERE/leg_geometry.py" --baseline "$OUT/eval/control" \
  --method "$OUT/eval/fg$WEIGHT" | tee "$OUT/legs.md"
