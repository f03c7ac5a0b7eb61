#!/usr/bin/env bash
# Ship the study's CPU checkpoints (docs/RESULTS.md) into depthnerf/checkpoints/ as fp16 safetensors + model cards:
#   bash scripts/export_study_checkpoints.sh [STUDY_DIR]      (after scripts/run_study.sh)
# cpu-<category>-depth = the bundled-prior run, cpu-<category>-baseline = the --depth none run,
# cpu-<category>-sym = the bundled-prior run with mirror-symmetric conditioning (RUNS "<category>-bundled-sym").
# cpu-<category>-sym-pp = the same with the prior read at each point too (RUNS "<category>-bundled-sym-pp").
# PAIRS (default "none:baseline bundled:depth") picks which, e.g. PAIRS="bundled-sym:sym" or "bundled-sym-pp:sym-pp";
# the run suffixes -sym -pp -rgb -x2 -np -nb (scripts/run_study.sh) become the flags of the card's command.
# STEPS: the runs' step count when the study ran with STEPS (recorded in the cards' command), e.g. STEPS=4000.
set -euo pipefail
STUDY=${1:-study}
for cat in ${CATEGORIES:-cars chairs}; do
  for pair in ${PAIRS:-none:baseline bundled:depth}; do
    run=${pair%%:*} kind=${pair#*:} prior=${pair%%-*}
    prior=${prior%%:*} extra=""
    [[ "$run" == *-sym* ]] && extra=" --model.mirror true"
    [[ "$run" == *-pp* ]] && extra="$extra --model.prior_at_point true"
    [[ "$run" == *-rgb* ]] && extra="$extra --model.rgb_at_point true"
    [[ "$run" == *-gf* ]] && extra="$extra --model.global_features true"
    [[ "$run" == *-x2* ]] && extra="$extra --model.encoder.image_scale 2.0"
    [[ "$run" == *-np* ]] && extra="$extra --model.encoder.use_first_pool false"
    [[ "$run" == *-nb* ]] && extra="$extra --schedule.bbox_steps 0"
    python scripts/export_checkpoint.py --run "$STUDY/runs/$cat-$run" --name "cpu-$cat-$kind" \
      --eval-summary "$STUDY/eval/$cat-$run/summary.json" --data-root "$STUDY/data" \
      --command "depthnerf train --preset cpu-$cat --data \$DATA --depth $prior$extra --seed 0${STEPS:+ --max-steps $STEPS} --out $STUDY/runs/$cat-$run  # via: ${STEPS:+STEPS=$STEPS }bash scripts/run_study.sh $STUDY"
  done
done
