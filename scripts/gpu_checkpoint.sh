#!/usr/bin/env bash
# Train a checkpoint to ship, on a lent GPU, in one device call (issue 19, item 4). The data is the synthetic
# benchmark the cpu-* checkpoints were trained on (`depthnerf synth`, seed 0, 64 px, 50 views an object: each object
# is seeded by its split and index alone, so these are the same train objects, and the 50 test objects here stay
# unseen), the model by default the app's cpu-*-sym-pp recipe (the cpu preset's architecture, which fits the
# repository's size budget, with mirror symmetry and the prior read at each point; MODEL_ARGS), trained for what
# the call leaves. Evaluation and the decision to ship happen on the CPU machine afterwards (docs/speed.md, "The
# next lease").
#
#   CATEGORY=cars bash scripts/gpu_checkpoint.sh OUT_DIR      (device call: carry [".whl"], timeout_s 600)
#
# Stages, each logged to OUT_DIR/gpu_checkpoint_log.txt with its seconds and exit code in gpu_checkpoint.json:
#  1. data: the train split, TRAIN_OBJECTS (300) x VIEWS (50) views at RES (64) px, SYNTH_WORKERS processes (nproc).
#     With embreex in .whl (`WHEELS="trimesh==5.2.0 rtree==1.4.1 lpips==0.1.4 embreex==4.4.0.post1" bash
#     scripts/gpu_wheels.sh`) Embree casts the rays on the machine's cores; without it torch does, on CUDA, slowly.
#  2. priors: the bundled depth net DEPTH_NET (srn) over the train split, on DEVICE (cuda).
#  3. store: the train split's views decoded once (--data.view_store), so that the probe's time is all steps.
#  4. probe: PROBE_SECONDS (90) of training with the preset's own schedule (its bbox phase first), stopped with
#     SIGTERM, which checkpoints. Its median ms per step over the second half of its logged steps sets STEPS.
#  5. main: --init-from the probe's weights, whole-image rays, a half-cosine learning rate LR (3e-4) -> LR_FINAL
#     (3e-6) over STEPS = (SECONDS_TOTAL - elapsed - RESERVE_S - START_S) * 1000 / (ms per step), START_S (25) the
#     run's start-up (imports, the store's check, a compilation with --compile-step: raise it then); at the deadline
#     SIGTERM stops it anyway (a checkpoint, the schedule then not at its end).
#  6. out: OUT_DIR/run.tar.gz (both run folders without optimiser states and TensorBoard events, the main run with
#     its last checkpoint only: what `depthnerf eval --checkpoint` and scripts/export_checkpoint.py read),
#     gpu_checkpoint.json (stages, both runs' ms per step, steps, first and last loss) and the log.
#  7. eval (EVAL_OBJECTS test objects; default 0, none): in what the call has left after the archive (over 40 s),
#     the testdata/testpriors stages make the first EVAL_OBJECTS of the test split the cpu-* cards were scored on
#     (50 there), `depthnerf eval` (the cards' protocol, --views-stride 25, EVAL_ARGS) scores the main run and
#     INIT side by side, and scripts/paired_difference.py pairs them: OUT_DIR/eval_main_summary.json and
#     OUT_DIR/eval_paired.md, the scores in gpu_checkpoint.json. Each evaluation stops at the call's end.
# Two calls on one warm machine (the device tool keeps it, with /tmp, for 30 s after a call): SECONDS_TOTAL is the
# whole budget the main run is planned for, CALL_SECONDS (SECONDS_TOTAL) this call's share, where SIGTERM stops the
# main run with a checkpoint; the next call, with CONTINUE=1 and its own CALL_SECONDS, resumes it (--resume) on the
# same plan (WORK/plan.txt) and packs the run again.
# Other settings: SEED (0), DATA_WORKERS (8, the loader's; the runs read a store of decoded views), INIT (a
# checkpoint the probe starts from, e.g. cpu-cars-sym-pp; default none), TRAIN_ARGS (extra train flags for both
# runs, e.g. --compile-step, or tiny sizes for a CPU smoke run), WORK (/tmp/depthnerf-gpu-checkpoint).
set -u
OUT=${1:?usage: gpu_checkpoint.sh OUT_DIR}
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$HERE/scripts/gpu_env.sh"
T0=$SECONDS
CATEGORY=${CATEGORY:-cars}; RES=${RES:-64}; TRAIN_OBJECTS=${TRAIN_OBJECTS:-300}; VIEWS=${VIEWS:-50}
SYNTH_WORKERS=${SYNTH_WORKERS:-$(nproc)}; DEPTH_NET=${DEPTH_NET:-srn}; DEVICE=${DEVICE:-cuda}; SEED=${SEED:-0}
SECONDS_TOTAL=${SECONDS_TOTAL:-540}; PROBE_SECONDS=${PROBE_SECONDS:-90}; RESERVE_S=${RESERVE_S:-30}
START_S=${START_S:-25}; CALL_SECONDS=${CALL_SECONDS:-$SECONDS_TOTAL}; CONTINUE=${CONTINUE:-}
EVAL_OBJECTS=${EVAL_OBJECTS:-0}; read -r -a EVAL_ARGS <<<"${EVAL_ARGS:-}"
LR=${LR:-3e-4}; LR_FINAL=${LR_FINAL:-3e-6}; DATA_WORKERS=${DATA_WORKERS:-8}; INIT=${INIT:-}
WORK=${WORK:-/tmp/depthnerf-gpu-checkpoint}
read -r -a MODEL_ARGS <<<"${MODEL_ARGS:---model.mirror true --model.prior_at_point true}"
read -r -a TRAIN_ARGS <<<"${TRAIN_ARGS:-}"
if [ -n "$CONTINUE" ] && [ ! -f "$WORK/plan.txt" ]; then
  echo "gpu_checkpoint: CONTINUE=1 but $WORK/plan.txt is missing: no planned main run on this machine to continue" >&2
  exit 2
fi
[ -n "$CONTINUE" ] || rm -rf "$WORK"
mkdir -p "$WORK" "$OUT"
LOG="$OUT/gpu_checkpoint_log.txt"; : >"$LOG"
STAGES="$WORK/stages.txt"; [ -n "$CONTINUE" ] || : >"$STAGES"
stage() {  # stage NAME CMD...: run, log, record "NAME rc seconds"
  local name=$1 s0=$SECONDS rc; shift
  echo "== $name: $*" >>"$LOG"
  "$@" >>"$LOG" 2>&1; rc=$?
  echo "$name $rc $((SECONDS - s0))" | tee -a "$LOG" >>"$STAGES"
  return $rc
}
train() {  # train RUN_NAME SECONDS FLAGS...: one run under timeout (SIGTERM checkpoints it)
  local run=$1 limit=$2; shift 2
  timeout -s TERM -k 30 "$limit" "$PY" -m depthnerf train --preset "cpu-$CATEGORY" --data "$WORK/data" \
    --depth bundled --depth-checkpoint "$DEPTH_NET" --seed "$SEED" --device "$DEVICE" --log.val_every 0 \
    --log.log_every 25 --no-progress --data.resolution "$RES" --data.num_workers "$DATA_WORKERS" \
    --data.view_store "$WORK/store" --out "$WORK/runs/$run" "${MODEL_ARGS[@]}" "$@" "${TRAIN_ARGS[@]}"
}
ms_per_step() { "$PY" "$HERE/scripts/step_rate.py" "$WORK/runs/$1"; }  # median ms per step, 2nd half
latest_weights() { echo "$WORK/runs/$1/checkpoints/$(cat "$WORK/runs/$1/checkpoints/latest")/model.safetensors"; }

call_left() { echo $(( CALL_SECONDS - (SECONDS - T0) - RESERVE_S )); }  # seconds this call can still train
# main_run SECONDS [--resume]: the planned main run; on --resume with the same flags again, so that a run stopped
# before its first checkpoint starts as planned
main_run() {
  if [ "$1" -lt 1 ]; then  # `timeout 0` would mean no limit at all
    echo "main: no time left in this call ($1 s); CONTINUE=1 in the next call runs it" | tee -a "$LOG" >&2
    return 1
  fi
  stage main train main "$@" --init-from "$(latest_weights probe)" --max-steps "$STEPS" \
    --checkpoint-every $(( STEPS / 4 > 0 ? STEPS / 4 : 1 )) --schedule.bbox_steps 0 --schedule.lr_schedule cosine \
    --schedule.lr "$LR" --schedule.lr_final "$LR_FINAL"
}
if [ -n "$CONTINUE" ]; then  # a later call on the same (warm) machine: the planned main run, resumed
  read -r STEPS MS <"$WORK/plan.txt"
  echo "continuing the main run (planned: $STEPS steps at $MS ms per step); $(call_left) s in this call" >>"$LOG"
  main_run "$(call_left)" --resume
else
  stage data "$PY" -m depthnerf synth --category "$CATEGORY" --out "$WORK/data" --train-objects "$TRAIN_OBJECTS" \
    --val-objects 0 --test-objects 0 --resolution "$RES" --views-train "$VIEWS" --seed 0 --workers "$SYNTH_WORKERS" \
    --quiet
  stage priors "$PY" -m depthnerf depth --data "$WORK/data" --depth bundled --depth-checkpoint "$DEPTH_NET" \
    --category "$CATEGORY" --resolution "$RES" --splits train --device "$DEVICE"
  # the decoded-view store, before the probe, whose time limit is then all steps (600 objects: 18 s on the H200)
  stage store "$PY" -c "import sys; from depthnerf.data.srn import index_split; from depthnerf.data.view_store import \
  ViewStore; from depthnerf.train.config import preset; root, cat, res = sys.argv[1], sys.argv[2], int(sys.argv[4]); \
  records = index_split(root, cat, 'train').objects; \
  ViewStore(sys.argv[3], res, preset('cpu-' + cat).data.pixel_center).ensure(records)" \
    "$WORK/data" "$CATEGORY" "$WORK/store" "$RES"
  init=(); [ -n "$INIT" ] && init=(--init-from "$INIT")
  stage probe train probe "$PROBE_SECONDS" --max-steps 10000000 --checkpoint-every 10000000 "${init[@]}"
  MS=$(ms_per_step probe 2>>"$LOG")
  LEFT=$(( SECONDS_TOTAL - (SECONDS - T0) - RESERVE_S ))
  STEPS=$("$PY" -c "import sys; ms, s = sys.argv[1:]; print(max(int(float(s) * 1000 / float(ms)), 1) if ms else 0)" \
    "$MS" "$(( LEFT - START_S ))")
  echo "probe: ${MS:-?} ms per step; $LEFT s left for the main run: $STEPS steps" >>"$LOG"
  [ -n "$MS" ] || echo "probe: too few logged steps for a step rate in $PROBE_SECONDS s: no main run" \
    "(raise PROBE_SECONDS)" | tee -a "$LOG" >&2
  if [ "$STEPS" -gt 0 ] && [ -f "$WORK/runs/probe/checkpoints/latest" ]; then
    LIMIT=$(call_left); [ "$LIMIT" -lt "$LEFT" ] || LIMIT=$LEFT
    echo "$STEPS $MS" >"$WORK/plan.txt"
    main_run "$LIMIT"
  fi
fi
if [ -f "$WORK/runs/main/checkpoints/latest" ]; then  # the run folders, less optimiser states, TensorBoard events
  rm -rf "$WORK/pack"; mkdir -p "$WORK/pack"             # and every checkpoint but the main run's last
  cp -r "$WORK/runs/main" "$WORK/runs/probe" "$WORK/pack/"
  keep=$(cat "$WORK/runs/main/checkpoints/latest")
  rm -rf "$WORK/pack/probe/checkpoints" "$WORK/pack/"*/tb
  find "$WORK/pack/main/checkpoints" -mindepth 1 -maxdepth 1 -type d ! -name "$keep" -exec rm -rf {} +
  rm -f "$WORK/pack/main/checkpoints/$keep/optimizer.safetensors"
  tar -C "$WORK/pack" -czf "$OUT/run.tar.gz" main probe
fi
# eval: the main run (and INIT, the model it continues) on the test objects, by the cards' protocol, in what the
# call has left after the archive; paired per object (scripts/paired_difference.py) when both finish
if [ "$EVAL_OBJECTS" -gt 0 ] && [ -f "$WORK/runs/main/checkpoints/latest" ] \
    && [ $(( CALL_SECONDS - (SECONDS - T0) )) -gt 40 ]; then
  if [ ! -d "$WORK/test" ]; then  # the test objects of the cpu-* cards (each seeded by its split and index)
    stage testdata "$PY" -m depthnerf synth --category "$CATEGORY" --out "$WORK/test" --train-objects 0 \
      --val-objects 0 --test-objects "$EVAL_OBJECTS" --resolution "$RES" --seed 0 --workers "$SYNTH_WORKERS" --quiet
    stage testpriors "$PY" -m depthnerf depth --data "$WORK/test" --depth bundled --depth-checkpoint "$DEPTH_NET" \
      --category "$CATEGORY" --resolution "$RES" --splits test --device "$DEVICE"
  fi
  EVAL_LEFT=$(( CALL_SECONDS - (SECONDS - T0) - 5 ))
  evaluate() {  # evaluate NAME CHECKPOINT: one evaluation under the call's time left
    timeout -s TERM -k 10 "$EVAL_LEFT" "$PY" -m depthnerf eval --checkpoint "$2" --data "$WORK/test" --split test \
      --out "$WORK/eval/$1" --views-stride 25 --device "$DEVICE" --no-progress --overwrite "${EVAL_ARGS[@]}"
  }
  s0=$SECONDS; rm -rf "$WORK/eval"
  evaluate main "$WORK/runs/main" >>"$LOG" 2>&1 & main_pid=$!
  [ -z "$INIT" ] || { evaluate init "$INIT" >>"$LOG" 2>&1; echo "eval-init $? $((SECONDS - s0))" >>"$STAGES"; }
  wait $main_pid; echo "eval-main $? $((SECONDS - s0))" | tee -a "$LOG" >>"$STAGES"
  [ -f "$WORK/eval/main/summary.json" ] && cp "$WORK/eval/main/summary.json" "$OUT/eval_main_summary.json"
  if [ -f "$WORK/eval/init/summary.json" ] && [ -f "$WORK/eval/main/summary.json" ]; then
    "$PY" "$HERE/scripts/paired_difference.py" --baseline "$WORK/eval/init" --method "$WORK/eval/main" \
      >"$OUT/eval_paired.md" 2>>"$LOG"
  fi
fi
MAIN_MS=$(ms_per_step main 2>>"$LOG")
"$PY" - "$WORK" "$OUT/gpu_checkpoint.json" "${MS:-}" "${MAIN_MS:-}" "$STEPS" "$CATEGORY" "$((SECONDS - T0))" <<'PY'
import json, sys
from pathlib import Path
work, out, ms, main_ms, steps, category, wall = Path(sys.argv[1]), Path(sys.argv[2]), *sys.argv[3:]
stages = {n: {"rc": int(rc), "seconds": int(s)} for n, rc, s in
          (line.split() for line in (work / "stages.txt").read_text().splitlines())}
runs = {}
for run in ("probe", "main"):
    m = work / "runs" / run / "metrics.jsonl"
    rows = [r for r in (json.loads(x) for x in m.read_text().splitlines()) if "loss" in r] if m.exists() else []
    latest = work / "runs" / run / "checkpoints" / "latest"
    runs[run] = {"last_step": rows[-1]["step"] if rows else None, "first_loss": rows[0]["loss"] if rows else None,
                 "last_loss": rows[-1]["loss"] if rows else None,
                 "checkpoint": latest.read_text().strip() if latest.exists() else None}
scores = {}
for name in ("main", "init"):
    summary = work / "eval" / name / "summary.json"
    if summary.exists():
        d = json.loads(summary.read_text())
        scores[name] = {k: d.get(k) for k in ("objects", "psnr", "ssim", "chamfer_l1", "fscore")}
res = {"category": category, "stages": stages, "eval": scores, "probe_ms_per_step": float(ms) if ms else None,
       "main_ms_per_step": float(main_ms) if main_ms else None,
       "main_steps_planned": int(steps), "runs": runs, "wall_s": int(wall),
       "packed": (out.parent / "run.tar.gz").exists()}
out.write_text(json.dumps(res, indent=1))
print(json.dumps(res, indent=1))
PY
if [ ! -f "$WORK/runs/main/checkpoints/latest" ]; then
  echo "gpu_checkpoint: no main run checkpoint (the log says why): $LOG" >&2
  exit 1
fi
