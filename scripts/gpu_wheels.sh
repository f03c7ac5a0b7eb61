#!/usr/bin/env bash
# Fetch, HERE (where pip reaches PyPI), the packages the lent GPU machine lacks, as one xz archive of their
# unpacked wheels: <checkout>/.whl/site.tar.xz (git-ignored, ~1.5 MB). That machine has torch 2.11 and most of the
# dependencies but no package registry (device README and KINDS.md); of what `python -m pytest` needs, it lacks
# trimesh, rtree (meshes) and lpips (one test). It lacks embreex too, which is left out: its Embree library makes
# the archive ~6.3 MB, which beside the checkout's 60.6 MB of tracked files passes the device tool's limit on what
# travels (64 MB, measured: 66.9 MB refused); there `depthnerf synth` casts rays with torch on CUDA instead
# (`--raycaster auto`, depthnerf/data/synth/hits.py), and the one test that compares the two engines skips.
# Send it with the device tool's `carry: [".whl"]`; scripts/gpu_env.sh unpacks it there into Python's site-packages.
# scripts/gpu_checkpoint.sh makes 15,000 views there and wants Embree: with the tracked files at 54.4 MB the archive
# with embreex (6.4 MB) fits (60.8 MB in all, `python scripts/travel_size.py .whl`):
#
#   bash scripts/gpu_wheels.sh          # Python 3.12, x86-64 manylinux (the GPU machine's)
#   WHEELS="trimesh==5.2.0 rtree==1.4.1 lpips==0.1.4 embreex==4.4.0.post1" bash scripts/gpu_wheels.sh
set -euo pipefail
HERE=$(cd "$(dirname "$0")/.." && pwd)
PYVER=${PYVER:-3.12}
WHEELS=${WHEELS:-"trimesh==5.2.0 rtree==1.4.1 lpips==0.1.4"}
STAGE=$(mktemp -d)
trap 'rm -rf "$STAGE"' EXIT
# shellcheck disable=SC2086
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
  -d "$STAGE/wheels" $WHEELS
mkdir -p "$STAGE/site" "$HERE/.whl"
for w in "$STAGE"/wheels/*.whl; do
  python3 -m zipfile -e "$w" "$STAGE/site"  # a wheel is a zip of its installed files (purelib = platlib here)
done
find "$STAGE/site" -name "*.so*" -exec chmod +x {} +
# Their debugging symbols off (smaller shared libraries; the archive must fit beside the tracked files)
if command -v strip >/dev/null; then
  find "$STAGE/site" -name "*.so*" -exec strip --strip-unneeded {} +
fi
rm -f "$HERE"/.whl/*.whl  # wheels an earlier version of this script left: they would travel too
tar -C "$STAGE/site" -cf - . | xz -9 -T2 > "$HERE/.whl/site.tar.xz"
ls "$STAGE/wheels"
ls -l "$HERE/.whl"
