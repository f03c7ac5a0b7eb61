#!/usr/bin/env bash
# Generalisation check (issue 13): the shipped checkpoints on synthetic test objects of a seed and a shape family
# they never saw, depth-aware vs baseline, with paired per-object differences.
#
#   bash scripts/generalisation_check.sh [OUT_DIR]        (default: study/generalisation, git-ignored)
#
# Per category: OBJECTS test objects of `depthnerf synth --family FAMILY --seed SEED --framing FRAMING` at 64 px
# (the CPU checkpoints' resolution), the depth priors cpu-<cat>-depth reads, `depthnerf eval` of cpu-<cat>-depth and
# cpu-<cat>-baseline (SRN protocol: input view 64, every STRIDE-th other view), then
# scripts/paired_difference.py (depth - baseline) into OUT_DIR/paired_<cat>.{md,json}.
#
# Environment: SEED (default 4242; training used 0, the bundled depth net's evaluation 1234, the demo 2718),
# FAMILY (heldout: microcars and hybrid chairs, never in the training grammar; `standard` gives the reference on
# the same seed), FRAMING (default: the framing of <prefix>-<first category>-depth's training data, from its
# spec; the shipped checkpoints are srn-framed), OBJECTS (20), STRIDE (25), CATEGORIES ("cars chairs"),
# CHECKPOINT_PREFIX (cpu: cpu-<cat>-{depth,baseline}), MESH (0: no Chamfer/F-score; 1: also geometry).
# Resumable: data and finished evaluations (summary.json) are kept.
set -euo pipefail
OUT=${1:-study/generalisation}
SEED=${SEED:-4242}
FAMILY=${FAMILY:-heldout}
CATEGORIES=${CATEGORIES:-cars chairs}
PREFIX=${CHECKPOINT_PREFIX:-cpu}
first_cat=${CATEGORIES%% *}
FRAMING=${FRAMING:-$(python "$(dirname "$0")/checkpoint_framing.py" "$PREFIX-$first_cat-depth")}
OBJECTS=${OBJECTS:-20}
STRIDE=${STRIDE:-25}
MESH=${MESH:-0}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
DATA="$OUT/data"
mesh=()
[ "$MESH" = 1 ] || mesh=(--no-mesh)

for cat in $CATEGORIES; do
  depthnerf synth --category "$cat" --out "$DATA" --train-objects 0 --val-objects 0 --test-objects "$OBJECTS" \
    --resolution 64 --seed "$SEED" --family "$FAMILY" --framing "$FRAMING" --quiet
done
for cat in $CATEGORIES; do
  depthnerf depth --data "$DATA" --for "$PREFIX-$cat-depth" --splits test --category "$cat" --no-progress
  for kind in baseline depth; do
    ev="$OUT/eval/$PREFIX-$cat-$kind"
    [ -f "$ev/summary.json" ] || depthnerf eval --checkpoint "$PREFIX-$cat-$kind" --data "$DATA" --split test \
      --views-stride "$STRIDE" "${mesh[@]}" --out "$ev" --no-progress
  done
  python "$(dirname "$0")/paired_difference.py" --baseline "$OUT/eval/$PREFIX-$cat-baseline" \
    --method "$OUT/eval/$PREFIX-$cat-depth" --json "$OUT/paired_$cat.json" | tee "$OUT/paired_$cat.md"
done
