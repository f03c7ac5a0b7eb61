"""Check that an editable install imports the package, not a ``depthnerf/`` clone folder in the current directory.

    python scripts/check_editable_install.py [--no-build-isolation] [--keep]

A clone is a folder named ``depthnerf/`` that holds the package folder ``depthnerf/``. Python in the folder that
holds the clone finds the clone folder first on its path (the current directory comes first); with no
``__init__.py`` there it is a namespace-package candidate. An editable install through setuptools' import finder
(a meta-path finder that runs after Python's own path search) then loses: ``import depthnerf`` gives the empty
namespace package and ``from depthnerf import Reconstructor`` fails with "unknown location". A static ``.pth``
entry (what ``[tool.setuptools] package-dir`` in ``pyproject.toml`` selects) puts the repository on the path,
where the real package wins over any namespace candidate.

What it does: makes ``TMP/holder/depthnerf/`` (``pyproject.toml`` and ``README.md`` copied, the package folder
linked), ``pip install --no-deps -e`` it into ``TMP/site`` (``--target``), then from ``TMP/holder`` runs
``python -S`` (without ``PYTHONPATH``) with ``TMP/site`` processed as a site directory (``site.addsitedir``: the ``.pth`` files run as at
start-up, after the current directory is on the path; ``-S`` keeps this interpreter's own install out of it) and
checks that ``import depthnerf`` is the linked package. ``--no-build-isolation`` builds with the setuptools
installed here (no download; needs setuptools >= 70.1, or >= 68 with ``wheel``). Prints one line; exit 0 when
the package is imported, 1 when it is shadowed, 2 when the install itself failed.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

PROBE = """
import site, sys
site.addsitedir(sys.argv[1])
import depthnerf
print(getattr(depthnerf, "__file__", None), getattr(depthnerf, "__version__", None))
"""


def check(tmp: Path, build_isolation: bool) -> tuple[int, str]:
    """(exit status, one line) of the check in the empty folder ``tmp``."""
    clone = tmp / "holder" / "depthnerf"
    clone.mkdir(parents=True)
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, clone / name)
    (clone / "depthnerf").symlink_to(ROOT / "depthnerf", target_is_directory=True)
    cmd = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--disable-pip-version-check",
           "--target", str(tmp / "site"), "-e", str(clone)]
    if not build_isolation:
        cmd.insert(4, "--no-build-isolation")
    install = subprocess.run(cmd, capture_output=True, text=True)
    if install.returncode != 0:
        return 2, f"pip install -e failed: {' '.join(install.stderr.split())[-600:]}"
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}  # a checkout put on it would win (gpu_env.sh)
    probe = subprocess.run([sys.executable, "-S", "-c", PROBE, str(tmp / "site")], capture_output=True, text=True,
                           cwd=clone.parent, env=env)
    expected = clone / "depthnerf" / "__init__.py"
    found = probe.stdout.split()[0] if probe.stdout.split() else None
    if probe.returncode == 0 and found == str(expected):
        return 0, f"ok: from {clone.parent}, `import depthnerf` is the installed package ({expected})"
    return 1, (f"shadowed: from {clone.parent}, `import depthnerf` gave {found or 'an error'} instead of "
               f"{expected} {' '.join(probe.stderr.split())[-300:]}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-build-isolation", action="store_true",
                        help="build with the setuptools installed here (no download)")
    parser.add_argument("--keep", action="store_true", help="keep the temporary folder (printed)")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="depthnerf-editable-"))
    try:
        status, line = check(tmp, not args.no_build_isolation)
    finally:
        if args.keep:
            print(f"kept {tmp}")
        else:
            shutil.rmtree(tmp, ignore_errors=True)
    print(line)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
