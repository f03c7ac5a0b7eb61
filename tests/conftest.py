"""Shared pytest fixtures. Builders live in ``tests/fixtures_srn.py`` (importable from any test module).

rembg's model folders point at an empty temporary folder for the whole session, so a background model that a
developer downloaded never changes what the tests see (``depthnerf.reconstruct.background``).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

import pytest
from fixtures_srn import make_srn_fixture

REMBG_HOME = pytest.StashKey[str]()


def pytest_configure(config) -> None:
    empty = tempfile.mkdtemp(prefix="depthnerf-tests-rembg-")
    config.stash[REMBG_HOME] = empty
    os.environ["U2NET_HOME"] = os.environ["REMBG_HOME"] = empty  # subprocesses inherit it


def pytest_unconfigure(config) -> None:
    shutil.rmtree(config.stash.get(REMBG_HOME, ""), ignore_errors=True)


@pytest.fixture
def srn_root(tmp_path: Path) -> Path:
    """A fresh tiny SRN cars folder: ``cars_train`` (2 objects) and ``cars_test`` (1), 3 views of 16x16."""
    return make_srn_fixture(tmp_path / "srn")


@pytest.fixture
def srn_root_full(tmp_path: Path) -> Path:
    """Like ``srn_root`` with depth, masks and meshes, and a ``cars_val`` split."""
    return make_srn_fixture(tmp_path / "srn", splits={"train": 2, "val": 1, "test": 1}, with_depth=True,
                            with_mask=True, with_mesh=True)
