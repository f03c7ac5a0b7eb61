# Sourced by scripts/gpu_check.sh and scripts/run_gpu_study.sh: the environment for running this checkout
# where it is not installed (the lent GPU machine: torch 2.11, no package registry, no `depthnerf` entry point).
#
# - PY: the Python that holds torch (env PYTHON, else python3, else python).
# - The checkout goes first on PYTHONPATH, so `$PY -m depthnerf` and tests' subprocesses import it.
# - The packages in <checkout>/.whl/site.tar.xz (made here by scripts/gpu_wheels.sh, sent with the device tool's
#   carry [".whl"]) are unpacked into PY's own site-packages, unless they already import, so that every
#   subprocess finds them, also tests that set their own PYTHONPATH; where that folder is not writable, into
#   GPU_SITE (default /tmp/depthnerf-gpu-site), put on PYTHONPATH.
# - `depthnerf` is a shell function for `$PY -m depthnerf` when no entry point is on PATH.
HERE=${HERE:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)}
if [ -z "${PY:-}" ]; then
  PY=${PYTHON:-$(command -v python3 || command -v python)}
fi
export PY
export PYTHONPATH="$HERE${PYTHONPATH:+:$PYTHONPATH}"
GPU_SITE=${GPU_SITE:-/tmp/depthnerf-gpu-site}
if [ -f "$HERE/.whl/site.tar.xz" ] && ! "$PY" -c "import trimesh, rtree, lpips" 2>/dev/null; then
  # Python unpacks it (its lzma module), so the machine needs no xz program
  unpack() { "$PY" -c "import sys, tarfile; tarfile.open(sys.argv[1]).extractall(sys.argv[2], filter='tar')" "$@"; }
  SITE=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['purelib'])")
  if [ -w "$SITE" ] && unpack "$HERE/.whl/site.tar.xz" "$SITE"; then
    :
  else
    mkdir -p "$GPU_SITE" && unpack "$HERE/.whl/site.tar.xz" "$GPU_SITE" \
      || echo "gpu_env: unpacking $HERE/.whl/site.tar.xz failed" >&2
    export PYTHONPATH="$PYTHONPATH:$GPU_SITE"
  fi
fi
if ! command -v depthnerf >/dev/null 2>&1; then
  depthnerf() { "$PY" -m depthnerf "$@"; }
fi
