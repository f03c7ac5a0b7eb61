#!/usr/bin/env bash
# A real `depthnerf train --compile-step` run beside an eager one on the same data (issue 19), short enough for
# what is left of a lease after the check: usage `SECONDS_EACH=60 bash scripts/gpu_compile_train.sh OUT_DIR`.
# Makes 4 synthetic cars x 16 views at 128 px, then trains paper-cars (--depth oracle, seed 0) eagerly and with
# --compile-step, each for at most SECONDS_EACH seconds of steps (--max-steps STEPS, default 400; the run is
# stopped by `timeout` with SIGTERM, which checkpoints), and writes OUT_DIR/compile_train.json: per run the steps
# done, the median ms per step over the second half of its logged steps (from metrics.jsonl's rays_per_s), the
# first and last loss, and the exit code; the logs go to OUT_DIR/compile_train_logs.txt.
set -u
OUT=${1:?usage: gpu_compile_train.sh OUT_DIR}
HERE=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
source "$HERE/scripts/gpu_env.sh"
WORK=${WORK:-/tmp/depthnerf-compile-train}; SECONDS_EACH=${SECONDS_EACH:-60}; STEPS=${STEPS:-400}
rm -rf "$WORK"; mkdir -p "$WORK" "$OUT"
LOG="$OUT/compile_train_logs.txt"
"$PY" -m depthnerf synth --category cars --out "$WORK/data" --train-objects 4 --val-objects 0 --test-objects 0 \
  --resolution 128 --views-train 16 --seed 0 --workers 8 --quiet >>"$LOG" 2>&1 || echo "synth failed" >>"$LOG"
for run in eager compiled; do
  extra=(); [ "$run" = compiled ] && extra=(--compile-step)
  s0=$SECONDS
  timeout -s TERM "$SECONDS_EACH" "$PY" -m depthnerf train --preset paper-cars --data "$WORK/data" --depth oracle \
    --seed 0 --max-steps "$STEPS" --checkpoint-every 100000 --device cuda --log.val_every 0 --log.log_every 1 \
    --no-progress --data.resolution 128 --data.num_workers 2 --out "$WORK/runs/$run" "${extra[@]}" >>"$LOG" 2>&1
  echo "$run rc=$? wall=$((SECONDS - s0))" | tee -a "$LOG" >"$WORK/$run.rc"
done
"$PY" - "$WORK" "$OUT/compile_train.json" <<'PY'
import json, statistics, sys
from pathlib import Path
work, out = Path(sys.argv[1]), Path(sys.argv[2])
res = {}
for run in ("eager", "compiled"):
    rc_line = (work / f"{run}.rc").read_text().split() if (work / f"{run}.rc").exists() else []
    m = work / "runs" / run / "metrics.jsonl"
    rows = [json.loads(x) for x in m.read_text().splitlines()] if m.exists() else []
    rows = [r for r in rows if "loss" in r]
    rates = [r["rays_per_s"] for r in rows if r.get("rays_per_s")]
    half = rates[len(rates) // 2:]
    res[run] = {"rc_wall": rc_line, "steps_logged": len(rows),
                "last_step": rows[-1]["step"] if rows else None,
                "median_rays_per_s_second_half": statistics.median(half) if half else None,
                "first_loss": rows[0]["loss"] if rows else None, "last_loss": rows[-1]["loss"] if rows else None,
                "keys": sorted(rows[-1]) if rows else []}
out.write_text(json.dumps(res, indent=1))
print(json.dumps(res, indent=1))
PY
