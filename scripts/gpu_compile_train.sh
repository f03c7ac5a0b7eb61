#!/usr/bin/env bash
# A real `depthnerf train --compile-step` run beside an eager one on the same data (issue 19), short enough for
# what is left of a lease after the check: usage `SECONDS_EACH=60 bash scripts/gpu_compile_train.sh OUT_DIR`.
# Makes 4 synthetic cars x VIEWS views (default 16) at 128 px, then trains paper-cars (--depth oracle, seed 0) once
# per name in RUNS (default "eager compiled"): `eager`, `compiled` (--compile-step), and either with `-store`
# appended (reading --data.view_store instead of decoding the PNG files), each for at most SECONDS_EACH seconds
# of steps (--max-steps STEPS, default 400; the run is stopped by `timeout` with SIGTERM, which checkpoints), with
# WORKERS data workers (default 2; DEVICE, RES and extra TRAIN_ARGS for a smoke run elsewhere), and writes
# OUT_DIR/compile_train.json: per run the steps done, the median rays_per_s over the second half of its logged
# steps (metrics.jsonl) and the median ms per step over them (scripts/step_rate.py), the first and last loss, and
# the exit code; the logs go to OUT_DIR/compile_train_logs.txt.
set -u
OUT=${1:?usage: gpu_compile_train.sh OUT_DIR}
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$HERE/scripts/gpu_env.sh"
WORK=${WORK:-/tmp/depthnerf-compile-train}; SECONDS_EACH=${SECONDS_EACH:-60}; STEPS=${STEPS:-400}
RUNS=${RUNS:-"eager compiled"}; VIEWS=${VIEWS:-16}; WORKERS=${WORKERS:-2}
DEVICE=${DEVICE:-cuda}; RES=${RES:-128}; read -r -a TRAIN_ARGS <<<"${TRAIN_ARGS:-}"  # a CPU smoke run: tiny flags
rm -rf "$WORK"; mkdir -p "$WORK" "$OUT"
LOG="$OUT/compile_train_logs.txt"
"$PY" -m depthnerf synth --category cars --out "$WORK/data" --train-objects 4 --val-objects 0 --test-objects 0 \
  --resolution "$RES" --views-train "$VIEWS" --seed 0 --workers 8 --quiet >>"$LOG" 2>&1 || echo "synth failed" >>"$LOG"
for run in $RUNS; do
  extra=()
  case "$run" in compiled*) extra+=(--compile-step) ;; esac
  case "$run" in *-store) extra+=(--data.view_store "$WORK/store") ;; esac
  s0=$SECONDS
  timeout -s TERM -k 30 "$SECONDS_EACH" "$PY" -m depthnerf train --preset paper-cars --data "$WORK/data" --depth oracle \
    --seed 0 --max-steps "$STEPS" --checkpoint-every 100000 --device "$DEVICE" --log.val_every 0 --log.log_every 1 \
    --no-progress --data.resolution "$RES" --data.num_workers "$WORKERS" --out "$WORK/runs/$run" "${extra[@]}" \
    "${TRAIN_ARGS[@]}" >>"$LOG" 2>&1
  echo "$run rc=$? wall=$((SECONDS - s0))" | tee -a "$LOG" >"$WORK/$run.rc"
done
"$PY" - "$WORK" "$OUT/compile_train.json" "$HERE/scripts" $RUNS <<'PY'
import json, statistics, sys
from pathlib import Path
sys.path.insert(0, sys.argv[3])
from step_rate import ms_per_step  # scripts/step_rate.py
work, out = Path(sys.argv[1]), Path(sys.argv[2])
res = {}
for run in sys.argv[4:]:
    rc_line = (work / f"{run}.rc").read_text().split() if (work / f"{run}.rc").exists() else []
    m = work / "runs" / run / "metrics.jsonl"
    rows = [json.loads(x) for x in m.read_text().splitlines()] if m.exists() else []
    rows = [r for r in rows if "loss" in r]
    rates = [r["rays_per_s"] for r in rows if r.get("rays_per_s")]
    half = rates[len(rates) // 2:]
    res[run] = {"rc_wall": rc_line, "steps_logged": len(rows),
                "last_step": rows[-1]["step"] if rows else None,
                "median_rays_per_s_second_half": statistics.median(half) if half else None,
                "ms_per_step": ms_per_step(work / "runs" / run),
                "first_loss": rows[0]["loss"] if rows else None, "last_loss": rows[-1]["loss"] if rows else None,
                "keys": sorted(rows[-1]) if rows else []}
out.write_text(json.dumps(res, indent=1))
print(json.dumps(res, indent=1))
PY
