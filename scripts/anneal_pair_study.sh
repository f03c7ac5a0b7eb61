#!/usr/bin/env bash
# The depth prior alone at equal budget, annealed (docs/RESULTS.md, "The depth prior alone, annealed"): the shipped
# cpu-<category>-baseline and cpu-<category>-depth are each warm-started (--init-from) and annealed the same way
# (seed 1, whole-image rays, a half-cosine learning rate 3e-4 -> 3e-6, 1500 steps), evaluated like the study (50 test
# objects, view stride 25) and paired per object: annealed depth vs annealed baseline, and each against its start.
# scripts/anneal_study.sh runs the chair pair with its other variants; this script runs one category's pair alone.
# Resumable: finished runs and evaluations are skipped, an interrupted run resumes from its last checkpoint.
#
#   bash scripts/anneal_pair_study.sh CATEGORY [OUT_DIR]   (cars | chairs; default OUT_DIR anneal-CATEGORY/, git-ignored;
#                                                           about 1 h on 2 cores after the data)
set -euo pipefail
CAT=${1:?usage: anneal_pair_study.sh cars|chairs [OUT_DIR]}
case "$CAT" in cars|chairs) ;; *) echo "anneal_pair_study.sh: category must be cars or chairs, not '$CAT'" >&2; exit 2;; esac
OUT=${2:-anneal-$CAT}
JOBS=${JOBS:-2}
STEPS=${STEPS:-1500}
export CAT OUT STEPS OMP_NUM_THREADS=1
mkdir -p "$OUT/logs" "$OUT/runs" "$OUT/eval"
[ -f "$OUT/data/${CAT}_card.json" ] || depthnerf synth --category "$CAT" --out "$OUT/data" --train-objects 300 \
  --val-objects 20 --test-objects 50 --resolution 64 --seed 0 --framing srn --workers "$JOBS" --quiet
depthnerf depth --data "$OUT/data" --estimator bundled --no-progress

one_run() {  # depth (none | bundled) and the shipped checkpoint it starts from
  set -euo pipefail
  local run="$OUT/runs/$CAT-$1-annealed"
  [ -f "$run/checkpoints/step_$(printf %08d "$STEPS")/model.safetensors" ] || depthnerf train --resume \
    --preset "cpu-$CAT" --data "$OUT/data" --depth "$1" --init-from "$2" --seed 1 --schedule.bbox_steps 0 \
    --schedule.lr_schedule cosine --schedule.lr 3e-4 --schedule.lr_final 3e-6 --max-steps "$STEPS" \
    --log.val_every 0 --out "$run" --no-progress > "$OUT/logs/train-$CAT-$1-annealed.log" 2>&1
  echo "trained $CAT-$1-annealed"
}
one_eval() {  # a run's name or a shipped checkpoint's name
  set -euo pipefail
  local ev="$OUT/eval/$1" src=(--run "$OUT/runs/$1")
  [ -d "$OUT/runs/$1" ] || src=(--checkpoint "$1")
  [ -f "$ev/summary.json" ] || depthnerf eval "${src[@]}" --data "$OUT/data" --views-stride 25 --save-renders \
    --out "$ev" --no-progress > "$OUT/logs/eval-$1.log" 2>&1
  echo "evaluated $1"
}
export -f one_run one_eval
printf '%s\n' "none cpu-$CAT-baseline" "bundled cpu-$CAT-depth" | xargs -P "$JOBS" -L 1 bash -c 'one_run $0 $1'
printf '%s\n' "$CAT-none-annealed" "$CAT-bundled-annealed" "cpu-$CAT-baseline" "cpu-$CAT-depth" \
  | xargs -P "$JOBS" -L 1 bash -c 'one_eval $0'

here=$(dirname "$0")
python "$here/paired_difference.py" --baseline "$OUT/eval/$CAT-none-annealed" --method "$OUT/eval/$CAT-bundled-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-$CAT-baseline" --method "$OUT/eval/$CAT-none-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-$CAT-depth" --method "$OUT/eval/$CAT-bundled-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-$CAT-baseline" --method "$OUT/eval/cpu-$CAT-depth"
