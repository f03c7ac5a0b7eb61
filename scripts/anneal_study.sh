#!/usr/bin/env bash
# Annealing the 4000-step chair model (docs/RESULTS.md, "Chairs: what was tried", "Annealing"): a warm start from its
# weights (--init-from), whole-image rays, a half-cosine learning rate down to 1/100, four variants; each evaluated
# like the study (50 test objects, view stride 25) and paired per object against the 4000-step model and today's
# cpu-chairs-depth / cpu-chairs-baseline; and the same annealing of cpu-chairs-baseline and cpu-chairs-depth (1500
# steps each: the depth prior alone at equal budget). The first variant is the shipped cpu-chairs-sym-pp. Resumable: finished
# runs and evaluations are skipped, an interrupted run resumes from its last checkpoint.
#
#   bash scripts/anneal_study.sh [OUT_DIR]      (default: anneal/, git-ignored; about 2 h on 2 cores)
set -euo pipefail
OUT=${1:-anneal}
JOBS=${JOBS:-2}
FROM=${FROM:-0fb4e8c}   # the commit whose cpu-chairs-sym-pp is the 4000-step model
export OUT OMP_NUM_THREADS=1
source "$(dirname "$0")/anneal_recipe.sh"
mkdir -p "$OUT/logs" "$OUT/runs" "$OUT/eval"
[ -f "$OUT/data/chairs_card.json" ] || depthnerf synth --category chairs --out "$OUT/data" --train-objects 300 \
  --val-objects 20 --test-objects 50 --resolution 64 --seed 0 --framing srn --workers "$JOBS" --quiet
depthnerf depth --data "$OUT/data" --estimator bundled --no-progress
[ -f "$OUT/sym-pp-4000.safetensors" ] || git show "$FROM:depthnerf/checkpoints/cpu-chairs-sym-pp.safetensors" \
  > "$OUT/sym-pp-4000.safetensors"

one_run() {  # name depth init lr lr_final steps objects; names *-sym-pp* / anneal-* are the mirror + prior-at-point model
  set -euo pipefail
  local run="$OUT/runs/$1" model=()
  [[ "$1" == anneal-* || "$1" == *sym-pp* ]] && model=(--model.mirror true --model.prior_at_point true)
  anneal_flags "$3" "$4" "$5"  # scripts/anneal_recipe.sh
  [ -f "$run/checkpoints/step_$(printf %08d "$6")/model.safetensors" ] || depthnerf train --resume --preset cpu-chairs \
    --data "$OUT/data" --depth "$2" "${model[@]}" --seed "$ANNEAL_SEED" "${ANNEAL_FLAGS[@]}" --max-steps "$6" \
    --schedule.objects_phase2 "$7" --out "$run" --no-progress > "$OUT/logs/train-$1.log" 2>&1
  echo "trained $1"
}
one_eval() {  # name (a run) or a shipped checkpoint name
  set -euo pipefail
  local ev="$OUT/eval/$1" src=(--run "$OUT/runs/$1")
  [ -d "$OUT/runs/$1" ] || src=(--checkpoint "$1")
  [ "$1" = sym-pp-4000 ] && src=(--checkpoint "$OUT/sym-pp-4000.safetensors")
  [ -f "$ev/summary.json" ] || depthnerf eval "${src[@]}" --data "$OUT/data" --views-stride 25 --save-renders \
    --out "$ev" --no-progress > "$OUT/logs/eval-$1.log" 2>&1
  echo "evaluated $1"
}
export -f one_run one_eval
S="$OUT/sym-pp-4000.safetensors"
printf '%s\n' "chairs-bundled-sym-pp-annealed bundled $S 3e-4 3e-6 3000 4" "anneal-1500-8obj bundled $S 3e-4 3e-6 1500 8" \
  "anneal-1500 bundled $S 3e-4 3e-6 1500 4" "anneal-1500-low bundled $S 1e-4 1e-6 1500 4" \
  "chairs-none-annealed none cpu-chairs-baseline 3e-4 3e-6 1500 4" \
  "chairs-bundled-annealed bundled cpu-chairs-depth 3e-4 3e-6 1500 4" \
  | xargs -P "$JOBS" -L 1 bash -c 'one_run $0 $1 $2 $3 $4 $5 $6'
printf '%s\n' chairs-bundled-sym-pp-annealed anneal-1500-8obj anneal-1500 anneal-1500-low sym-pp-4000 \
  cpu-chairs-depth cpu-chairs-baseline chairs-none-annealed chairs-bundled-annealed | xargs -P "$JOBS" -L 1 bash -c 'one_eval $0'

here=$(dirname "$0")
python "$here/paired_difference.py" --baseline "$OUT/eval/sym-pp-4000" --method "$OUT/eval/anneal-1500" \
  "$OUT/eval/anneal-1500-low" "$OUT/eval/anneal-1500-8obj" "$OUT/eval/chairs-bundled-sym-pp-annealed"
for ref in cpu-chairs-depth cpu-chairs-baseline; do
  python "$here/paired_difference.py" --baseline "$OUT/eval/$ref" --method "$OUT/eval/chairs-bundled-sym-pp-annealed"
done
python "$here/angle_bins.py" --baseline "$OUT/eval/cpu-chairs-depth" --method "$OUT/eval/chairs-bundled-sym-pp-annealed"
# the depth prior alone at equal budget: baseline and depth-aware checkpoints, each annealed the same way
python "$here/paired_difference.py" --baseline "$OUT/eval/chairs-none-annealed" --method "$OUT/eval/chairs-bundled-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-chairs-baseline" --method "$OUT/eval/chairs-none-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-chairs-depth" --method "$OUT/eval/chairs-bundled-annealed"
python "$here/angle_bins.py" --baseline "$OUT/eval/sym-pp-4000" --method "$OUT/eval/chairs-bundled-sym-pp-annealed"
python "$here/qualitative_figure.py" --evals "$OUT/eval/cpu-chairs-depth" "$OUT/eval/sym-pp-4000" \
  "$OUT/eval/chairs-bundled-sym-pp-annealed" --labels cpu-chairs-depth "cpu-chairs-sym-pp (4000 steps)" \
  "annealed (+3000 steps, cosine)" --data "$OUT/data" --objects 4 --view 25 --out "$OUT/chairs_annealed.png"
