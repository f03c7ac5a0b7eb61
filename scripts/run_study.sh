#!/usr/bin/env bash
# The offline benchmark study of issue 7 (docs/RESULTS.md): synthetic SRN-protocol data -> bundled depth priors ->
# 6 training runs (cars/chairs x baseline/bundled/oracle, equal steps and seed) -> SRN-protocol eval -> Table 1
# -> figures. Every stage is resumable: rerunning the script skips finished work and resumes training runs from
# their last checkpoint.
#
#   bash scripts/run_study.sh [STUDY_DIR]        (default: study/, git-ignored)
#
# Environment: STEPS (training steps, default: the preset's 2000), JOBS (runs in parallel, default 2, each with
# one thread: on 2 cores, two 1-thread jobs beat one 2-thread job), STRIDE (eval view stride, default 25),
# RUNS (which runs, default all six, e.g. "cars-none cars-bundled"; a "-sym" suffix, e.g. "cars-bundled-sym", adds
# mirror-symmetric conditioning, "-dl" the scale/shift-invariant depth loss at weight DEPTH_LOSS, default 10, "-pp" the
# prior read at each point, --model.prior_at_point, "-rgb" the colour, --model.rgb_at_point, "-gf" global features,
# --model.global_features, "-x2" the
# encoder on the input upsampled 2x, "-np" the encoder without its first max-pool, "-nb" no bbox-sampling phase, "-s<N>" training seed N instead of 0 (the data's seed stays 0), "-an" (last) the run
# without "-an" trained first, then warm-started from its best checkpoint and annealed by the recipe of scripts/anneal_recipe.sh
# (ANNEAL_STEPS, default 1500, of a cosine learning rate 3e-4 -> 3e-6, whole-image rays, seed 1), "-w" the bundled prior
# from the depth net DEPTH_WEIGHTS (a weights file or a shipped net's name) instead of BUNDLED_NET (--depth-checkpoint;
# its priors are cached beside the others, keyed by the file's hash); suffixes combine, e.g.
# "cars-bundled-sym-pp", "cars-bundled-pp-s1"), CATEGORIES (whose data to make, default "cars chairs"), FRAMING (synthetic benchmark framing,
# default srn: framed as SRN's renders, docs/data.md; `legacy` reproduces the data of the shipped cpu-*
# checkpoints), PIXEL_CENTER (the runs' data.pixel_center, default 0.0 = the paper presets' pixelNeRF reading;
# 0.5 reads the SRN-framed renders exactly), RES (images and training resolution, default 64; 128 is SRN's and the
# paper presets'), GENERALISATION (1: also run scripts/generalisation_check.sh on
# the checkpoints exported from this study: set CHECKPOINT_PREFIX to their name prefix; default 0), BUNDLED_NET (the
# shipped bundled depth net of the "bundled" runs, default srn; the sections of docs/RESULTS.md measured before srn
# shipped used legacy, depthnerf/depth/weights/MODEL_CARD.md).
# The shipped cpu-* checkpoints were trained with FRAMING=legacy; re-running with the default framing and
# re-exporting them (scripts/export_study_checkpoints.sh) moves them to the SRN framing.
set -euo pipefail
STUDY=${1:-study}
JOBS=${JOBS:-2}
STRIDE=${STRIDE:-25}
RUNS=${RUNS:-"cars-none cars-bundled chairs-none chairs-bundled cars-oracle chairs-oracle"}
SEED=0
FRAMING=${FRAMING:-srn}
PIXEL_CENTER=${PIXEL_CENTER:-0.0}
RES=${RES:-64}
BUNDLED_NET=${BUNDLED_NET:-srn}
export BUNDLED_NET STUDY STRIDE SEED FRAMING PIXEL_CENTER RES STEPS=${STEPS:-}
export OMP_NUM_THREADS=1
source "$(dirname "$0")/anneal_recipe.sh"
mkdir -p "$STUDY/logs"

# 1. data: 300 train / 20 val / 50 test objects per category at RES px (default 64, the CPU presets' resolution)
for cat in ${CATEGORIES:-cars chairs}; do
  depthnerf synth --category "$cat" --out "$STUDY/data" --train-objects 300 --val-objects 20 --test-objects 50 \
    --resolution "$RES" --seed "$SEED" --framing "$FRAMING" --workers "$JOBS" --quiet
done
# 2. bundled depth priors for every split (oracle priors need no cache: they come from the GT depth)
depthnerf depth --data "$STUDY/data" --estimator bundled --depth-checkpoint "$BUNDLED_NET" --no-progress
if [ -n "${DEPTH_WEIGHTS:-}" ]; then
  depthnerf depth --data "$STUDY/data" --estimator bundled --depth-checkpoint "$DEPTH_WEIGHTS" --no-progress
fi
export DEPTH_WEIGHTS=${DEPTH_WEIGHTS:-}

# 3. + 4. train and evaluate each run
one_run() {
  set -euo pipefail  # not inherited through xargs: a failed training must not be evaluated
  local name=$1 cat=${1%%-*} rest=${1#*-}
  local prior=${rest%%-*}
  local variants=${rest#"$prior"}
  local run="$STUDY/runs/$name" ev="$STUDY/eval/$name" log="$STUDY/logs/$name.log"
  local steps=() extra=() variant seed=$SEED net=()
  [ "$prior" = bundled ] && net=(--depth-checkpoint "$BUNDLED_NET")
  [ -n "$STEPS" ] && steps=(--max-steps "$STEPS")
  for variant in ${variants//-/ }; do
    case "$variant" in
      sym) extra+=(--model.mirror true) ;;  # mirror-symmetric conditioning (docs/RESULTS.md, "Symmetry")
      dl) extra+=(--schedule.depth_loss_weight "${DEPTH_LOSS:-10}") ;;  # depth as supervision ("Depth loss")
      pp) extra+=(--model.prior_at_point true) ;;  # the prior read at each point ("Source pixels at the point")
      rgb) extra+=(--model.rgb_at_point true) ;;  # the colour read at each point (same section)
      gf) extra+=(--model.global_features true) ;;  # image-wide features at every point ("Global features")
      x2) extra+=(--model.encoder.image_scale 2.0) ;;  # encoder on the input upsampled 2x ("Chairs: what was tried")
      np) extra+=(--model.encoder.use_first_pool false) ;;  # encoder without its first max-pool (same section)
      nb) extra+=(--schedule.bbox_steps 0) ;;  # no bbox-sampling phase: whole images from step 0 (same section)
      s[0-9]*) seed=${variant#s} ;;  # another training seed: the spread between runs ("A rerun does not reproduce it")
      an) [ "${name%-an}" != "$name" ] || { echo "run $name: variant 'an' must come last" >&2; return 2; }
          one_run "${name%-an}"  # the run it starts from, trained and evaluated first
          anneal_flags "$STUDY/runs/${name%-an}"; extra+=("${ANNEAL_FLAGS[@]}")  # scripts/anneal_recipe.sh
          steps=(--max-steps "${ANNEAL_STEPS:-1500}"); seed=$ANNEAL_SEED ;;
      w) [ -n "$DEPTH_WEIGHTS" ] || { echo "run $name: variant 'w' needs DEPTH_WEIGHTS (a bundled depth net)" >&2; return 2; }
         net=(--depth-checkpoint "$DEPTH_WEIGHTS") ;;  # another bundled depth net ("A depth net trained on the SRN framing")
      *) echo "unknown run variant '$variant' in $name (known: sym, dl, pp, rgb, x2, np, nb, s<N>, w, an)" >&2; return 2 ;;
    esac
  done
  if [ ! -f "$ev/summary.json" ]; then
    local resume=()
    [ -f "$run/config.json" ] && resume=(--resume)
    depthnerf train --preset "cpu-$cat" --data "$STUDY/data" --depth "$prior" --seed "$seed" --out "$run" \
      --data.pixel_center "$PIXEL_CENTER" --data.resolution "$RES" "${steps[@]}" "${extra[@]}" "${net[@]}" "${resume[@]}" --no-progress >> "$log" 2>&1
    depthnerf eval --run "$run" --views-stride "$STRIDE" --save-renders --out "$ev" --no-progress >> "$log" 2>&1
  fi
  echo "$name done"
}
export -f one_run
printf '%s\n' $RUNS | xargs -P "$JOBS" -I{} bash -c 'one_run {}'

# 5. table and figures
evals=()
for name in chairs-none chairs-bundled chairs-oracle cars-none cars-bundled cars-oracle; do
  [ -f "$STUDY/eval/$name/summary.json" ] && evals+=("$STUDY/eval/$name")
done
if [ ${#evals[@]} -eq 0 ]; then  # e.g. RUNS="cars-bundled-pp-s1" alone: no Table-1 run to tabulate
  echo "run_study.sh: none of Table 1's six runs is evaluated in $STUDY: no table or figures"; exit 0
fi
depthnerf compare "${evals[@]}" --reference paper --out "$STUDY/table.md"
mkdir -p "$STUDY/figures"
python scripts/plot_training_curves.py --runs "$STUDY"/runs/* --out "$STUDY/figures/training_curves.png"
for cat in cars chairs; do
  ce=()
  for prior in none bundled oracle; do
    [ -f "$STUDY/eval/$cat-$prior/summary.json" ] && ce+=("$STUDY/eval/$cat-$prior")
  done
  python scripts/qualitative_figure.py --evals "${ce[@]}" --data "$STUDY/data" --objects 4 \
    --out "$STUDY/figures/qualitative_$cat.png"
done
for cat in cars chairs; do
  others=()
  for prior in bundled oracle; do
    [ -f "$STUDY/eval/$cat-$prior/summary.json" ] && others+=("$STUDY/eval/$cat-$prior")
  done
  [ -f "$STUDY/eval/$cat-none/summary.json" ] && [ ${#others[@]} -gt 0 ] && \
    python scripts/paired_difference.py --baseline "$STUDY/eval/$cat-none" --method "${others[@]}" \
      --json "$STUDY/paired_$cat.json" | tee "$STUDY/paired_$cat.md"
done
cat "$STUDY/table.md"

# 6. optional: generalisation check (unseen seed and shape family) of checkpoints exported from this study
if [ "${GENERALISATION:-0}" = 1 ]; then
  FRAMING="$FRAMING" bash scripts/generalisation_check.sh "$STUDY/generalisation"
fi
