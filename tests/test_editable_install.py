"""An editable install imports the package even from the folder that holds a ``depthnerf/`` clone folder
(``scripts/check_editable_install.py``: a real ``pip install -e`` into a temporary site directory)."""

from __future__ import annotations

import importlib.metadata
import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _version(name: str) -> tuple[int, ...]:
    try:
        return tuple(int(p) for p in importlib.metadata.version(name).split(".")[:2])
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return ()


OFFLINE_BUILD = _version("setuptools") >= (70, 1) or (_version("setuptools") >= (68,) and bool(_version("wheel")))


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("pip") is None or not OFFLINE_BUILD,
                    reason="needs pip and setuptools >= 70.1 (or >= 68 with wheel) to build without a download")
def test_a_clone_folder_in_the_current_directory_does_not_shadow_the_package():
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "check_editable_install.py"), "--no-build-isolation"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.startswith("ok: "), out.stdout + out.stderr
