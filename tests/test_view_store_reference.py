"""The view store (:mod:`depthnerf.data.view_store`) against the rules of its module docstring, file by file:
which files an object's fingerprint covers (a change to each one rebuilds the object, a change to another file
does not), a store of another pixel centre, a record with another number of views."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest
from fixtures_srn import make_srn_fixture

from depthnerf.data.srn import index_split
from depthnerf.data.view_store import ViewStore, store_fingerprint
from depthnerf.errors import DepthnerfError


def _touch(path: Path, size_change: bool) -> None:
    """A new modification time; with ``size_change`` also one byte more (a rewritten file)."""
    if size_change:
        with open(path, "ab") as f:
            f.write(b"\n")
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))


@pytest.mark.parametrize("size_change", [False, True])
def test_the_fingerprint_covers_intrinsics_rgb_pose_and_mask_files_only(tmp_path, size_change):
    """A new size or modification time of ``intrinsics.txt`` or of one view's RGB, pose or mask file changes the
    fingerprint; a new depth file or mesh (not held by the store) does not."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=3, size=16, with_mask=True,
                            with_depth=True, with_mesh=True)
    record = index_split(root, "cars", "train").objects[0]
    assert record.has_mask and record.has_depth and record.mesh_path is not None
    covered = [record.path / "intrinsics.txt", record.rgb_path(2), record.pose_path(1), record.mask_path(0)]
    for path in (record.depth_path(1), record.mesh_path, *covered):
        before = store_fingerprint(record)
        _touch(path, size_change)
        assert (store_fingerprint(record) != before) == (path in covered), path


def test_opening_an_object_for_a_record_with_other_views_is_refused(tmp_path):
    """The store holds 3 views of the object; a record of the same object with 2 views is one line naming both."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=3, size=8)
    record = index_split(root, "cars", "train").objects[0]
    ViewStore(tmp_path / "store", 8, 0.5).ensure([record])
    fewer = dataclasses.replace(record, view_names=record.view_names[:2])
    with pytest.raises(DepthnerfError, match=r"holds 3 views, the dataset has 2"):
        ViewStore(tmp_path / "store", 8, 0.5).open(fewer)
