#!/usr/bin/env bash
# The depth prior alone at equal budget, annealed (docs/RESULTS.md, "The depth prior alone, annealed"): the shipped
# cpu-<category>-baseline and cpu-<category>-depth are each warm-started (--init-from) and annealed the same way
# (seed 1, whole-image rays, a half-cosine learning rate 3e-4 -> 3e-6, 1500 steps), evaluated like the study (50 test
# objects, view stride 25) and paired per object: annealed depth vs annealed baseline, and each against its start.
# scripts/anneal_study.sh runs the chair pair with its other variants; this script runs one category's pair alone.
# With SYM_PP=1 (cars), also the shipped car model's annealing: the 2000-step mirror + prior-at-point model of commit
# c49b8f7 (FROM), continued 3000 steps the same way, which is today's cpu-cars-sym-pp; evaluated and paired against
# its start and the pair, with a by-angle table and the figure docs/figures/cars_annealed.png. With PP=1, the
# combination of the two recipes for the depth prior alone: prior at each point, then annealed.
# Resumable: finished runs and evaluations are skipped, an interrupted run resumes from its last checkpoint.
#
#   bash scripts/anneal_pair_study.sh CATEGORY [OUT_DIR]   (cars | chairs; default OUT_DIR anneal-CATEGORY/, git-ignored;
#                                                           about 1 h on 2 cores after the data)
#   SYM_PP=1 bash scripts/anneal_pair_study.sh cars      (about 40 minutes more)
#   PP=1 bash scripts/anneal_pair_study.sh CATEGORY      (the depth-aware run with the prior read at each point,
#                                                         trained 2000 steps and annealed the same way, paired against
#                                                         the annealed baseline; about 1 h more)
set -euo pipefail
CAT=${1:?usage: anneal_pair_study.sh cars|chairs [OUT_DIR]}
case "$CAT" in cars|chairs) ;; *) echo "anneal_pair_study.sh: category must be cars or chairs, not '$CAT'" >&2; exit 2;; esac
OUT=${2:-anneal-$CAT}
JOBS=${JOBS:-2}
STEPS=${STEPS:-1500}
export CAT OUT STEPS OMP_NUM_THREADS=1
source "$(dirname "$0")/anneal_recipe.sh"
mkdir -p "$OUT/logs" "$OUT/runs" "$OUT/eval"
[ -f "$OUT/data/${CAT}_card.json" ] || depthnerf synth --category "$CAT" --out "$OUT/data" --train-objects 300 \
  --val-objects 20 --test-objects 50 --resolution 64 --seed 0 --framing srn --workers "$JOBS" --quiet
depthnerf depth --data "$OUT/data" --estimator bundled --no-progress

anneal() {  # run name, the checkpoint it starts from, steps, then the run's own train flags (--depth, model options)
  set -euo pipefail
  local name=$1 from=$2 steps=$3
  shift 3
  local run="$OUT/runs/$name"
  anneal_flags "$from"  # scripts/anneal_recipe.sh
  [ -f "$run/checkpoints/step_$(printf %08d "$steps")/model.safetensors" ] || depthnerf train --resume \
    --preset "cpu-$CAT" --data "$OUT/data" "$@" --seed "$ANNEAL_SEED" "${ANNEAL_FLAGS[@]}" --max-steps "$steps" \
    --out "$run" --no-progress > "$OUT/logs/train-$name.log" 2>&1
  echo "trained $name"
}
one_run() {  # depth (none | bundled) and the shipped checkpoint it starts from
  anneal "$CAT-$1-annealed" "$2" "$STEPS" --depth "$1"
}
one_eval() {  # a run's name or a shipped checkpoint's name
  set -euo pipefail
  local ev="$OUT/eval/$1" src=(--run "$OUT/runs/$1")
  [ -d "$OUT/runs/$1" ] || src=(--checkpoint "$1")
  [ -f "$ev/summary.json" ] || depthnerf eval "${src[@]}" --data "$OUT/data" --views-stride 25 --save-renders \
    --out "$ev" --no-progress > "$OUT/logs/eval-$1.log" 2>&1
  echo "evaluated $1"
}
export -f anneal one_run one_eval
printf '%s\n' "none cpu-$CAT-baseline" "bundled cpu-$CAT-depth" | xargs -P "$JOBS" -L 1 bash -c 'one_run $0 $1'
printf '%s\n' "$CAT-none-annealed" "$CAT-bundled-annealed" "cpu-$CAT-baseline" "cpu-$CAT-depth" \
  | xargs -P "$JOBS" -L 1 bash -c 'one_eval $0'

here=$(dirname "$0")
python "$here/paired_difference.py" --baseline "$OUT/eval/$CAT-none-annealed" --method "$OUT/eval/$CAT-bundled-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-$CAT-baseline" --method "$OUT/eval/$CAT-none-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-$CAT-depth" --method "$OUT/eval/$CAT-bundled-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-$CAT-baseline" --method "$OUT/eval/cpu-$CAT-depth"

if [ "${PP:-0}" = 1 ]; then  # the depth prior read at each point, then annealed: the two recipes combined
  pp="$OUT/runs/$CAT-bundled-pp"  # as run_study.sh's "<cat>-bundled-pp": the cpu preset, 2000 steps, seed 0
  [ -f "$pp/checkpoints/step_00002000/model.safetensors" ] || depthnerf train --resume --preset "cpu-$CAT" \
    --data "$OUT/data" --depth bundled --model.prior_at_point true --seed 0 --out "$pp" --no-progress \
    > "$OUT/logs/train-$CAT-bundled-pp.log" 2>&1
  # from its best checkpoint, annealed as the pair above
  anneal "$CAT-bundled-pp-annealed" "$pp" "$STEPS" --depth bundled --model.prior_at_point true
  printf '%s\n' "$CAT-bundled-pp-annealed" "$CAT-bundled-pp" | xargs -P "$JOBS" -L 1 bash -c 'one_eval $0'
  python "$here/paired_difference.py" --baseline "$OUT/eval/$CAT-none-annealed" --method "$OUT/eval/$CAT-bundled-pp-annealed"
  python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-$CAT-baseline" --method "$OUT/eval/$CAT-bundled-pp"
  python "$here/paired_difference.py" --baseline "$OUT/eval/$CAT-bundled-pp" --method "$OUT/eval/$CAT-bundled-pp-annealed"
  python "$here/angle_bins.py" --baseline "$OUT/eval/$CAT-none-annealed" --method "$OUT/eval/$CAT-bundled-pp-annealed"
fi
[ "${SYM_PP:-0}" = 1 ] || exit 0
[ "$CAT" = cars ] || { echo "anneal_pair_study.sh: SYM_PP=1 is for cars (chairs: scripts/anneal_study.sh)" >&2; exit 2; }
FROM=${FROM:-c49b8f7}
START="$OUT/sym-pp-2000.safetensors"
[ -f "$START" ] || git show "$FROM:depthnerf/checkpoints/cpu-cars-sym-pp.safetensors" > "$START"
anneal cars-bundled-sym-pp-annealed "$START" 3000 --depth bundled --model.mirror true --model.prior_at_point true
[ -f "$OUT/eval/sym-pp-2000/summary.json" ] || depthnerf eval --checkpoint "$START" --data "$OUT/data" \
  --views-stride 25 --save-renders --out "$OUT/eval/sym-pp-2000" --no-progress > "$OUT/logs/eval-sym-pp-2000.log" 2>&1
one_eval cars-bundled-sym-pp-annealed
A="$OUT/eval/cars-bundled-sym-pp-annealed"
python "$here/paired_difference.py" --baseline "$OUT/eval/sym-pp-2000" --method "$A"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-cars-depth" --method "$A"
python "$here/paired_difference.py" --baseline "$OUT/eval/cpu-cars-baseline" --method "$A"
python "$here/angle_bins.py" --baseline "$OUT/eval/cpu-cars-depth" --method "$A"
python "$here/angle_bins.py" --baseline "$OUT/eval/sym-pp-2000" --method "$A"
python "$here/qualitative_figure.py" --evals "$OUT/eval/cpu-cars-depth" "$OUT/eval/sym-pp-2000" "$A" \
  --labels cpu-cars-depth "cpu-cars-sym-pp (2000 steps)" "annealed (+3000 steps, cosine)" --data "$OUT/data" \
  --objects 4 --view 25 --out "$OUT/cars_annealed.png"
