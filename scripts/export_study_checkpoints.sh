#!/usr/bin/env bash
# Ship the study's CPU checkpoints (docs/RESULTS.md) into depthnerf/checkpoints/ as fp16 safetensors + model cards:
#   bash scripts/export_study_checkpoints.sh [STUDY_DIR]      (after scripts/run_study.sh)
# cpu-<category>-depth = the bundled-prior run, cpu-<category>-baseline = the --depth none run.
set -euo pipefail
STUDY=${1:-study}
for cat in ${CATEGORIES:-cars chairs}; do
  for pair in none:baseline bundled:depth; do
    prior=${pair%%:*} kind=${pair#*:}
    python scripts/export_checkpoint.py --run "$STUDY/runs/$cat-$prior" --name "cpu-$cat-$kind" \
      --eval-summary "$STUDY/eval/$cat-$prior/summary.json" --data-root "$STUDY/data" \
      --command "depthnerf train --preset cpu-$cat --data \$DATA --depth $prior --seed 0 --out $STUDY/runs/$cat-$prior  # via: bash scripts/run_study.sh $STUDY"
  done
done
