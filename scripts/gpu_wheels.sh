#!/usr/bin/env bash
# Fetch, HERE (where pip reaches PyPI), the wheels the lent GPU machine lacks, into <checkout>/.whl (git-ignored).
# That machine has torch 2.11 and most of the dependencies but no package registry (device README and KINDS.md);
# of what `python -m pytest` needs, it lacks trimesh, embreex, rtree (synth, meshes) and lpips (one test).
# Send them with the device tool's `carry: [".whl"]`; scripts/gpu_env.sh installs them there (into /tmp).
#
#   bash scripts/gpu_wheels.sh          # ~16 MB; Python 3.12, x86-64 manylinux (the GPU machine's)
set -euo pipefail
HERE=$(cd "$(dirname "$0")/.." && pwd)
PYVER=${PYVER:-3.12}
WHEELS=${WHEELS:-"trimesh==5.2.0 embreex==4.4.0.post1 rtree==1.4.1 lpips==0.1.4"}
mkdir -p "$HERE/.whl"
# shellcheck disable=SC2086
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
  -d "$HERE/.whl" $WHEELS
ls -l "$HERE/.whl"
du -sh "$HERE/.whl"
