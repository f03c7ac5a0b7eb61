#!/usr/bin/env bash
# The mesh level rules (depthnerf/render/mesh_level.py: auto, silhouette, local) on the shipped car and chair models
# (docs/RESULTS.md, "Mesh level rules"): the study's 50 test objects per category (SRN framing, 64 px, seed 0: the
# same objects as scripts/run_study.sh; two train objects only, as nothing is trained here), bundled priors,
# `depthnerf eval` once per rule (view stride 25, renders and meshes saved), then the geometry paired per object
# against the auto level and the leg band of the chairs. Resumable: finished evaluations are skipped.
#
#   bash scripts/mesh_level_study.sh [OUT_DIR]      (default: mesh_levels/, git-ignored; about 1 h on 2 cores)
# CARS / CHAIRS: the checkpoints (default the shipped cpu-cars-sym-pp / cpu-chairs-sym-pp; docs/RESULTS.md measured
# the 4000-step chair model: CHAIRS=FILE with FILE from `git show 0fb4e8c:depthnerf/checkpoints/cpu-chairs-sym-pp.safetensors`).
set -euo pipefail
OUT=${1:-mesh_levels}
JOBS=${JOBS:-2}
CARS=${CARS:-cpu-cars-sym-pp}
CHAIRS=${CHAIRS:-cpu-chairs-sym-pp}
export OUT CARS CHAIRS OMP_NUM_THREADS=1
mkdir -p "$OUT/logs"
for cat in cars chairs; do
  [ -f "$OUT/data/${cat}_card.json" ] || depthnerf synth --category "$cat" --out "$OUT/data" --train-objects 2 \
    --val-objects 1 --test-objects 50 --resolution 64 --seed 0 --framing srn --workers "$JOBS" --quiet
done
depthnerf depth --data "$OUT/data" --estimator bundled --no-progress

one_eval() {
  set -euo pipefail
  local cat=$1 rule=$2 ev="$OUT/eval/$1-$2" ck=$CARS
  [ "$cat" = chairs ] && ck=$CHAIRS
  [ -f "$ev/summary.json" ] || depthnerf eval --checkpoint "$ck" --data "$OUT/data" --views-stride 25 \
    --save-renders --mesh-threshold "$rule" --method "$(basename "$ck" .safetensors), $rule mesh level" --out "$ev" --no-progress \
    > "$OUT/logs/$cat-$rule.log" 2>&1
  echo "$cat $rule done"
}
export -f one_eval
printf '%s\n' "chairs auto" "chairs silhouette" "chairs local" "cars auto" "cars silhouette" "cars local" \
  | xargs -P "$JOBS" -L 1 bash -c 'one_eval $0 $1'

here=$(dirname "$0")
for cat in cars chairs; do
  python "$here/paired_difference.py" --baseline "$OUT/eval/$cat-auto" --method "$OUT/eval/$cat-silhouette" \
    "$OUT/eval/$cat-local"
done
python "$here/leg_geometry.py" --baseline "$OUT/eval/chairs-auto" --method "$OUT/eval/chairs-silhouette" \
  "$OUT/eval/chairs-local"
