# Sourced by scripts/gpu_check.sh and scripts/run_gpu_study.sh: the environment for running this checkout
# where it is not installed (the lent GPU machine: torch 2.11, no package registry, no `depthnerf` entry point).
#
# - PY: the Python that holds torch (env PYTHON, else python3, else python).
# - The checkout goes first on PYTHONPATH, so `$PY -m depthnerf` and tests' subprocesses import it.
# - Wheels in <checkout>/.whl (made here by scripts/gpu_wheels.sh, sent with the device tool's carry [".whl"])
#   are installed, unless the packages they hold already import: into PY's own environment (so that every
#   subprocess finds them, also tests that set their own PYTHONPATH), else into GPU_SITE (default
#   /tmp/depthnerf-gpu-site), put on PYTHONPATH.
# - `depthnerf` is a shell function for `$PY -m depthnerf` when no entry point is on PATH.
HERE=${HERE:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)}
if [ -z "${PY:-}" ]; then
  PY=${PYTHON:-$(command -v python3 || command -v python)}
fi
export PY
export PYTHONPATH="$HERE${PYTHONPATH:+:$PYTHONPATH}"
GPU_SITE=${GPU_SITE:-/tmp/depthnerf-gpu-site}
if compgen -G "$HERE/.whl/*.whl" >/dev/null && ! "$PY" -c "import trimesh, embreex, rtree" 2>/dev/null; then
  if ! "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir "$HERE"/.whl/*.whl >&2; then
    "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$GPU_SITE" \
      "$HERE"/.whl/*.whl >&2 || echo "gpu_env: installing $HERE/.whl failed" >&2
    export PYTHONPATH="$PYTHONPATH:$GPU_SITE"
  fi
fi
if ! command -v depthnerf >/dev/null 2>&1; then
  depthnerf() { "$PY" -m depthnerf "$@"; }
fi
