#!/usr/bin/env bash
# One-command GPU check (issue 19): pytest on CUDA, benchmarks/bench_gpu.py, a --deterministic paper-preset run
# killed at a checkpoint stage and resumed, and two same-seed runs, compared bit for bit. Writes
# OUT_DIR/gpu_check.json (compact), OUT_DIR/gpu_check.log and OUT_DIR/pytest_report.jsonl. About 7.5 minutes on
# one H100 (GPU_CHECK_SECONDS=450); on a machine without CUDA the same stages run on the CPU with tiny sizes
# (CUDA-only parts recorded as skipped). Stages, settings and environment overrides: scripts/gpu_check.py.
#
#   bash scripts/gpu_check.sh OUT_DIR
#   GPU_CHECK_STAGES=pytest GPU_CHECK_SECONDS=540 bash scripts/gpu_check.sh OUT_DIR   # the tests alone
#
# On the lent GPU machine (no package registry): run scripts/gpu_wheels.sh here first and carry .whl
# (scripts/gpu_env.sh installs it there); the device tool's calls are in docs/speed.md, "Measuring on a lent GPU".
# Exit status: 0 when no stage failed, 1 otherwise (the JSON says which).
set -uo pipefail
OUT_DIR=${1:?usage: gpu_check.sh OUT_DIR}
HERE=$(cd "$(dirname "$0")/.." && pwd)
# shellcheck source=scripts/gpu_env.sh
source "$HERE/scripts/gpu_env.sh"
mkdir -p "$OUT_DIR"
export PYTHONUNBUFFERED=1
exec "$PY" "$HERE/scripts/gpu_check.py" "$OUT_DIR"
