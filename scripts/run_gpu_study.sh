#!/usr/bin/env bash
# Push-button GPU study (issue 12), resumable across calls (issue 19): synthetic cars and chairs at 128 px ->
# bundled depth priors -> baseline / bundled / oracle at the paper's model (paper-<category> presets), trained side
# by side on one GPU for a fixed number of steps that fits MINUTES -> SRN-protocol eval on the same test objects ->
# Table-1 style table (depthnerf compare) and paired per-object differences (scripts/paired_difference.py).
#
#   bash scripts/run_gpu_study.sh DIR [MINUTES]        (default 12 minutes in all: a 15-minute lease of one H100)
#
# Calls. One call works for at most CALL_SECONDS (default 480 s: a device-tool call is 10 minutes at most), then
# stops its training runs with SIGTERM (each writes a checkpoint at its current step) and exits 3: run the SAME
# command again to go on. Every stage skips finished work: data (synth resumes per object), priors (a done mark),
# the step rule (kept in DIR/study_state.env), training (--resume; runs that reached STEPS are left alone;
# checkpoints every CKPT_MIN minutes of training, default 2, so a call killed from outside loses at most that;
# the runs read the training views from one store of decoded views, DIR/views, built when they first start),
# evaluation (per-object results resume; a finished summary.json is kept), then the table. Exit 0: finished.
# State lives in DIR: on a lent GPU machine DIR survives only while the machine stays warm between calls
# (docs/speed.md, "Measuring on a lent GPU"); with no state in DIR the study starts from the beginning and says so.
#
# Time budget and the step rule (computed once, in the first call, and kept). MINUTES is split as: data + priors
# + step-rate probe ~ DATA_MIN (default 2), evaluation, the restart of the runs in each further call ~ RESUME_S
# (default 45 s), training = the rest. Evaluation is estimated as
#     eval_seconds = 30 + RUNS * TEST_OBJECTS * ceil((VIEWS_TEST - 1) / STRIDE) * VIEW_MS / 1000
# with VIEW_MS (default 200) the device's ms per 128 px view over all runs evaluating side by side (measured on one
# H100, eager: 6 runs x 200 views in 243 s; docs/speed.md). All RUNS (default 6) train concurrently on the one GPU,
# so each gets about 1/RUNS of it:
#     STEPS = floor(train_seconds * 1000 / (STEP_MS * RUNS))
# where STEP_MS is the measured ms per training iteration of ONE run alone (benchmarks/bench_gpu.py --no-views,
# run here first), or the env value STEP_MS if set. On one H100 six runs side by side made 24.4 steps/s in all, i.e.
# 41 ms per step-run: concurrency does not beat the sum there. bbox_steps = STEPS / 4 (the paper: 100k of 400k).
# Measured on one H100 (docs/speed.md): with STEP_MS=40 and 12 minutes the study finished in two calls, 480 s and
# 310 s (6 x 1562 steps; data and priors 108 s).
#
# Environment overrides (the CPU plumbing test sets tiny values): RES (128), TRAIN_OBJECTS (200), TEST_OBJECTS
# (20), VIEWS_TRAIN (50), VIEWS_TEST (251), STRIDE (eval view stride, 25: 10 views per object), STEPS (skip the
# rule), STEP_MS, VIEW_MS, EVAL_CHUNK (rays per eval pass, 16384: one view, ~3.5 GiB per run), DEVICE
# (auto), WORKERS (synth processes, nproc), CATEGORIES ("cars chairs"), PRIORS ("none bundled oracle"),
# TRAIN_ARGS (extra `depthnerf train` flags, e.g. model-size overrides), EVAL_ARGS (extra `depthnerf eval` flags,
# e.g. --compile or --guided), MESH (0: no mesh metrics), CALL_SECONDS,
# CKPT_MIN, CKPT_EVERY (steps; skips the CKPT_MIN rule), RESULTS_TO (a folder, e.g. the device tool's $OUT: each
# call ends by copying status.json, table.md, paired_*.md|json and logs.tar.gz there).
# Exit status: 0 finished, 3 not finished in this call (run it again), 1 a stage failed, 2 no step rate.
set -euo pipefail
DIR=${1:?usage: run_gpu_study.sh DIR [MINUTES]}
MINUTES=${2:-12}
RES=${RES:-128}; TRAIN_OBJECTS=${TRAIN_OBJECTS:-200}; TEST_OBJECTS=${TEST_OBJECTS:-20}
VIEWS_TRAIN=${VIEWS_TRAIN:-50}; VIEWS_TEST=${VIEWS_TEST:-251}; STRIDE=${STRIDE:-25}
DEVICE=${DEVICE:-auto}; WORKERS=${WORKERS:-$(nproc)}; DATA_MIN=${DATA_MIN:-2}; VIEW_MS=${VIEW_MS:-200}; EVAL_CHUNK=${EVAL_CHUNK:-16384}
CATEGORIES=${CATEGORIES:-"cars chairs"}; PRIORS=${PRIORS:-"none bundled oracle"}; TRAIN_ARGS=${TRAIN_ARGS:-}
MESH=${MESH:-0}; EVAL_ARGS=${EVAL_ARGS:-}; SEED=0; CALL_SECONDS=${CALL_SECONDS:-480}; CKPT_MIN=${CKPT_MIN:-2}; RESUME_S=${RESUME_S:-45}
HERE=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=scripts/gpu_env.sh
source "$HERE/scripts/gpu_env.sh"
DN=("$PY" -m depthnerf)  # a plain command (not the gpu_env function), so `&` gives the trainer's own pid
mkdir -p "$DIR/logs"
DIR=$(cd "$DIR" && pwd)
t_call=$(date +%s)
call_end=$(( t_call + CALL_SECONDS ))
left() { echo $(( call_end - $(date +%s) )); }
lim() { local l; l=$(left); [ "$l" -gt 0 ] && echo "$l" || echo 1; }  # for timeout, where 0 means no limit

runs=()
for cat in $CATEGORIES; do for prior in $PRIORS; do runs+=("$cat-$prior"); done; done

results() {  # copy what a person reads to RESULTS_TO (at most 8 files: the device tool's limit)
  [ -n "${RESULTS_TO:-}" ] || return 0
  mkdir -p "$RESULTS_TO"
  "$PY" - "$DIR" "${STEPS:-0}" "$1" "${runs[@]}" > "$RESULTS_TO/status.json" <<'PY' || true
import json, sys, time
from pathlib import Path
d, steps, state, runs = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4:]
def step(name):
    p = d / "runs" / name / "checkpoints" / "latest"
    return int(p.read_text().strip().split("_")[-1]) if p.is_file() else 0
print(json.dumps({"state": state, "steps_target": steps, "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                  "runs": {n: {"step": step(n), "eval_done": (d / "eval" / n / "summary.json").is_file()}
                           for n in runs},
                  "study_state": (d / "study_state.env").read_text() if (d / "study_state.env").is_file() else None},
                 indent=1))
PY
  for f in table.md paired_cars.md paired_cars.json paired_chairs.md paired_chairs.json; do
    [ -f "$DIR/$f" ] && cp "$DIR/$f" "$RESULTS_TO/"
  done
  (cd "$DIR" && tar -czf "$RESULTS_TO/logs.tar.gz" logs study_state.env runs/*/metrics.jsonl runs/*/launches.jsonl \
    eval/*/summary.json eval/*/per_object.csv 2>/dev/null) || true
}
finish() { results "$1"; exit "$2"; }
pids=()
on_signal() {  # stopped from outside (timeout, Ctrl+C): the runs checkpoint at their step, then exit 3
  trap - TERM INT
  for pid in "${pids[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
  for pid in "${pids[@]}"; do wait "$pid" 2>/dev/null || true; done
  echo "stopped by a signal: run the same command again to go on" >&2
  finish "call again" 3
}
trap on_signal TERM INT
out_of_time() { echo "this call's time is up ($CALL_SECONDS s) during $1: run the same command again to go on" >&2
  finish "call again" 3; }

if [ -f "$DIR/study_state.env" ]; then
  # shellcheck disable=SC1091
  source "$DIR/study_state.env"
  CALLS=$(( CALLS + 1 ))
  echo "resuming the study in $DIR (call $CALLS; $STEPS steps per run, checkpoint every $CKPT_EVERY)"
else
  CALLS=1
  echo "no earlier state in $DIR: starting the study from the beginning"
fi

# 1. data (test split with val too: the presets validate; validation is switched off below) and priors
for cat in $CATEGORIES; do
  [ -f "$DIR/data/${cat}_card.json" ] && continue
  [ "$(left)" -gt 0 ] || out_of_time "synth"
  timeout --signal=TERM "$(lim)" "${DN[@]}" synth --category "$cat" --out "$DIR/data" \
    --train-objects "$TRAIN_OBJECTS" --val-objects 1 --test-objects "$TEST_OBJECTS" --resolution "$RES" \
    --views-train "$VIEWS_TRAIN" --views-test "$VIEWS_TEST" --seed "$SEED" --workers "$WORKERS" --quiet \
    || { [ "$(left)" -le 0 ] && out_of_time "synth"; echo "synth $cat failed" >&2; finish failed 1; }
done
if [[ " $PRIORS " == *" bundled "* ]] && [ ! -f "$DIR/.priors_done" ]; then
  depth_device=$DEVICE
  [ "$depth_device" = auto ] && depth_device=$("$PY" -c "import torch; print('cuda' if torch.cuda.is_available() else 'cpu')")
  [ "$(left)" -gt 0 ] || out_of_time "priors"
  timeout --signal=TERM "$(lim)" "${DN[@]}" depth --data "$DIR/data" --estimator bundled --device "$depth_device" \
    --no-progress >> "$DIR/logs/depth.log" 2>&1 \
    || { [ "$(left)" -le 0 ] && out_of_time "priors"; echo "depth priors failed (see $DIR/logs/depth.log)" >&2
         finish failed 1; }
  touch "$DIR/.priors_done"
fi

# 2. the step rule (once; kept in study_state.env)
if [ ! -f "$DIR/study_state.env" ]; then
  if [ -z "${STEPS:-}" ]; then
    if [ -z "${STEP_MS:-}" ]; then
      "$PY" "$HERE/benchmarks/bench_gpu.py" --device "$DEVICE" --no-views --repeat 10 --json "$DIR/step_probe.json" \
        > "$DIR/logs/step_probe.log" 2>&1 || true
      STEP_MS=$("$PY" -c "import json,sys; print(json.load(open(sys.argv[1])).get('train_ms_best', ''))" \
        "$DIR/step_probe.json" 2>/dev/null || true)
      [ -n "$STEP_MS" ] || { echo "could not measure the step rate (no GPU?); set STEPS or STEP_MS" >&2; exit 2; }
    fi
    spent=$(( $(date +%s) - t_call ))
    calls=$(( (MINUTES * 60 + CALL_SECONDS - 1) / CALL_SECONDS ))
    eval_s=$("$PY" -c "import math; print(30 + math.ceil(${#runs[@]} * $TEST_OBJECTS * math.ceil(($VIEWS_TEST - 1) / $STRIDE) * $VIEW_MS / 1000))")
    train_s=$(( MINUTES * 60 - eval_s - (spent > DATA_MIN * 60 ? spent : DATA_MIN * 60) - (calls - 1) * RESUME_S ))
    STEPS=$("$PY" -c "print(max(1, int($train_s * 1000 / ($STEP_MS * ${#runs[@]}))))")
    echo "step rule: ${train_s} s of training (${eval_s} s kept for evaluation) / (${STEP_MS} ms per step x ${#runs[@]} runs) = $STEPS steps per run"
  fi
  if [ -z "${CKPT_EVERY:-}" ]; then
    CKPT_EVERY=$STEPS
    [ -n "${STEP_MS:-}" ] && CKPT_EVERY=$("$PY" -c "print(max(1, min($STEPS, int($CKPT_MIN * 60000 / ($STEP_MS * ${#runs[@]})))))")
  fi
  printf 'STEPS=%s\nCKPT_EVERY=%s\nSTEP_MS=%s\nCALLS=%s\n' "$STEPS" "$CKPT_EVERY" "${STEP_MS:-}" "$CALLS" \
    > "$DIR/study_state.env"
else
  sed -i "s/^CALLS=.*/CALLS=$CALLS/" "$DIR/study_state.env"
fi
BBOX=$(( STEPS / 4 > 0 ? STEPS / 4 : 1 ))

# 3. train side by side on one device; stop them (SIGTERM: a checkpoint at the current step) when the call is up
run_step() { local p="$DIR/runs/$1/checkpoints/latest"; [ -f "$p" ] && echo $(( 10#$(sed 's/step_//' "$p") )) || echo 0; }
names=()
for name in "${runs[@]}"; do
  [ "$(run_step "$name")" -ge "$STEPS" ] && continue
  cat=${name%%-*}; prior=${name#*-}
  # shellcheck disable=SC2086
  "${DN[@]}" train --preset "paper-$cat" --data "$DIR/data" --depth "$prior" --seed "$SEED" --out "$DIR/runs/$name" \
    --resume --device "$DEVICE" --max-steps "$STEPS" --checkpoint-every "$CKPT_EVERY" --schedule.bbox_steps "$BBOX" \
    --data.resolution "$RES" --data.num_workers 2 --data.view_store "$DIR/views" --log.val_every 0 --log.log_every 50 --no-progress $TRAIN_ARGS \
    >> "$DIR/logs/train-$name.log" 2>&1 &
  pids+=($!); names+=("$name")
done
[ ${#pids[@]} -gt 0 ] && echo "training ${names[*]} to step $STEPS ($(left) s left in this call)"
stopped=0
while :; do
  alive=0
  for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && alive=1; done
  [ $alive = 0 ] && break
  if [ "$(left)" -le 0 ] && [ $stopped = 0 ]; then
    for pid in "${pids[@]}"; do kill -TERM "$pid" 2>/dev/null || true; done
    stopped=1
  fi
  sleep 2
done
fail=0
for i in "${!pids[@]}"; do
  rc=0; wait "${pids[$i]}" || rc=$?
  [ $rc = 0 ] || [ $rc = 143 ] || { echo "training ${names[$i]} failed (exit $rc, see $DIR/logs)" >&2; fail=1; }
done
[ $fail = 0 ] || finish failed 1
[ $stopped = 1 ] && out_of_time "training (steps now: $(for n in "${runs[@]}"; do printf '%s=%s ' "$n" "$(run_step "$n")"; done))"

# 4. evaluate on the same test objects, 5. table and paired differences
mesh=(--no-mesh); [ "$MESH" = 1 ] && mesh=()
[ "$(left)" -gt 0 ] || out_of_time "evaluation"
epids=(); enames=()
for name in "${runs[@]}"; do  # side by side, as in training (one H100: 203 ms per view in all, 223 one run alone)
  [ -f "$DIR/eval/$name/summary.json" ] && continue
  # shellcheck disable=SC2086
  timeout --signal=TERM "$(lim)" "${DN[@]}" eval --run "$DIR/runs/$name" --views-stride "$STRIDE" --device "$DEVICE" \
    --chunk "$EVAL_CHUNK" --out "$DIR/eval/$name" "${mesh[@]}" --no-progress $EVAL_ARGS >> "$DIR/logs/eval-$name.log" 2>&1 &
  epids+=($!); enames+=("$name")
done
pids=("${epids[@]}")  # a signal from outside stops these too
timed_out=0; failed=0
for i in "${!epids[@]}"; do
  rc=0; wait "${epids[$i]}" || rc=$?
  [ $rc = 0 ] && continue
  if [ "$(left)" -le 0 ]; then timed_out=1  # stopped by this call's limit: the next call resumes it
  else echo "eval ${enames[$i]} failed (exit $rc, see $DIR/logs)" >&2; failed=1; fi
done
[ $timed_out = 0 ] || out_of_time "evaluation"
[ $failed = 0 ] || finish failed 1
evals=(); for name in "${runs[@]}"; do evals+=("$DIR/eval/$name"); done
"${DN[@]}" compare "${evals[@]}" --reference paper --out "$DIR/table.md" || finish failed 1
for cat in $CATEGORIES; do
  others=(); for prior in $PRIORS; do [ "$prior" != none ] && others+=("$DIR/eval/$cat-$prior"); done
  if [[ " $PRIORS " == *" none "* ]] && [ ${#others[@]} -gt 0 ]; then
    "$PY" "$HERE/scripts/paired_difference.py" --baseline "$DIR/eval/$cat-none" --method "${others[@]}" \
      --json "$DIR/paired_$cat.json" | tee "$DIR/paired_$cat.md" || finish failed 1
  fi
done
echo "study finished in call $CALLS ($STEPS steps per run): $DIR/table.md"
finish finished 0
