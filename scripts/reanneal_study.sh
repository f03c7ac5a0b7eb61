#!/usr/bin/env bash
# A second annealing of a shipped model (docs/RESULTS.md, "A second annealing of the shipped car model"): the
# shipped weights continued for STEPS steps with the annealing recipe (scripts/anneal_recipe.sh) at two peak
# learning rates, each run and the shipped model scored on the study's test objects, paired per object, and again
# on TEST objects of an unseen seed. About 75 minutes for cars on an idle 2-core machine (two runs side by side,
# one thread each); resumable: every stage skips finished work.
#
#   bash scripts/reanneal_study.sh DIR                      # cars, cpu-cars-sym-pp
#   CATEGORY=chairs CHECKPOINT=cpu-chairs-sym-pp bash scripts/reanneal_study.sh DIR
#   STEPS=4 TRAIN=3 VAL=1 TEST=2 UNSEEN=2 bash scripts/reanneal_study.sh /tmp/r   # a smoke run of the script
#   TRAIN=1200 ARMS="3e-4:3e-6" bash scripts/reanneal_study.sh DIR  # the lr-3e-4 arm on four times the train objects
# (synth seeds each object by its split and index alone, so the first 300 train objects and the test objects are
# those of the 300-object data)
set -euo pipefail
OUT=$1
CATEGORY=${CATEGORY:-cars}
CHECKPOINT=${CHECKPOINT:-cpu-$CATEGORY-sym-pp}
STEPS=${STEPS:-3000}
TRAIN=${TRAIN:-300}
VAL=${VAL:-20}
TEST=${TEST:-50}
UNSEEN=${UNSEEN:-20}
RES=${RES:-64}
SEED=${SEED:-2}
ARMS=${ARMS:-3e-4:3e-6 1e-4:1e-6}  # PEAK:FINAL learning rates, one run each
HERE=$(cd "$(dirname "$0")" && pwd)
source "$HERE/anneal_recipe.sh"
mkdir -p "$OUT"
export OMP_NUM_THREADS=1

data() {  # data() DIR SEED TRAIN VAL TEST: the study's framing and size, priors cached for the shipped net
  [ -f "$1/${CATEGORY}_card.json" ] || depthnerf synth --category "$CATEGORY" --out "$1" --train-objects "$3" \
    --val-objects "$4" --test-objects "$5" --resolution "$RES" --seed "$2" --framing srn --workers 2 --quiet
  depthnerf depth --data "$1" --for "$CHECKPOINT" --no-progress
}
score() {  # score() DATA CHECKPOINT OUT
  [ -f "$3/summary.json" ] || depthnerf eval --checkpoint "$2" --data "$1" --split test --out "$3" \
    --views-stride 25 --no-progress
}

data "$OUT/data" 0 "$TRAIN" "$VAL" "$TEST"
data "$OUT/unseen" 4242 0 0 "$UNSEEN"
for arm in $ARMS; do
  lr=${arm%%:*}
  run="$OUT/runs/lr$lr"
  anneal_flags "$CHECKPOINT" "$lr" "${arm##*:}"
  [ -d "$run/checkpoints/step_$(printf %08d "$STEPS")" ] || depthnerf train --preset "cpu-$CATEGORY" \
    --data "$OUT/data" --depth bundled --depth-checkpoint srn --model.mirror true --model.prior_at_point true \
    --seed "$SEED" "${ANNEAL_FLAGS[@]}" --max-steps "$STEPS" --checkpoint-every 250 --out "$run" --resume \
    --no-progress > "$OUT/train_lr$lr.log" 2>&1 &
done
wait
score "$OUT/data" "$CHECKPOINT" "$OUT/eval/shipped"
score "$OUT/unseen" "$CHECKPOINT" "$OUT/eval-unseen/shipped"
methods=() unseen=()
for arm in $ARMS; do
  lr=${arm%%:*}
  score "$OUT/data" "$OUT/runs/lr$lr" "$OUT/eval/lr$lr"
  score "$OUT/unseen" "$OUT/runs/lr$lr" "$OUT/eval-unseen/lr$lr"
  methods+=("$OUT/eval/lr$lr") unseen+=("$OUT/eval-unseen/lr$lr")
done
python "$HERE/paired_difference.py" --baseline "$OUT/eval/shipped" --method "${methods[@]}" | tee "$OUT/paired.md"
python "$HERE/paired_difference.py" --baseline "$OUT/eval-unseen/shipped" --method "${unseen[@]}" \
  | tee "$OUT/paired_unseen.md"
