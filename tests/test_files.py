"""``depthnerf.files``: atomic writes and file hashes against hashlib and the file system."""

from __future__ import annotations

import hashlib
import json
import os

import pytest

from depthnerf.errors import DepthnerfError
from depthnerf.files import (
    file_problem,
    folder_problem,
    make_folder,
    sha256_file,
    sha256_files,
    write_bytes_atomic,
    write_json_atomic,
    write_text_atomic,
)


def test_atomic_writes_replace_and_leave_no_temporary(tmp_path):
    path = tmp_path / "sub" / "state.json"
    write_json_atomic(path, {"b": 1, "a": [1, 2]})
    assert path.read_text() == json.dumps({"a": [1, 2], "b": 1}, indent=2) + "\n"
    write_text_atomic(path, "new\n")
    assert path.read_text() == "new\n"
    assert sorted(p.name for p in path.parent.iterdir()) == ["state.json"]


def test_hashes_match_hashlib(tmp_path):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(bytes(range(256)) * 5000)  # > one 1 MiB read block
    b.write_bytes(b"xyz")
    assert sha256_file(a) == hashlib.sha256(a.read_bytes()).hexdigest()
    named = hashlib.sha256(b"a.bin\0" + a.read_bytes() + b"b.bin\0" + b"xyz").hexdigest()
    assert sha256_files([a, b]) == named
    assert sha256_files([a, b], names=False) == hashlib.sha256(a.read_bytes() + b"xyz").hexdigest()


def test_make_folder_makes_parents_and_names_a_file_in_the_way(tmp_path):
    made = make_folder(tmp_path / "a" / "b", "--out")
    assert made.is_dir() and make_folder(made, "--out") == made  # an existing folder is fine
    (tmp_path / "f").write_text("x")
    assert folder_problem(tmp_path / "f", "--out") == f"{tmp_path / 'f'}: --out is a file, not a folder"
    deep = tmp_path / "f" / "x" / "y"
    assert folder_problem(deep, "--out") == f"{deep}: --out lies under {tmp_path / 'f'}, which is a file, not a folder"
    with pytest.raises(DepthnerfError, match="lies under"):
        make_folder(deep, "--out")
    assert not (tmp_path / "f").is_dir()


def test_file_problem_names_a_folder_or_a_file_in_the_way(tmp_path):
    (tmp_path / "f").write_text("x")
    assert file_problem(tmp_path / "new" / "out.json", "--json") is None  # a missing parent is made when written
    assert file_problem(tmp_path / "f", "--json") is None  # an existing file is replaced
    assert file_problem(tmp_path, "--json") == f"{tmp_path}: --json is a folder; name the file to write"
    deep = tmp_path / "f" / "x" / "out.json"
    assert file_problem(deep, "--json") == f"{deep}: --json lies under {tmp_path / 'f'}, which is a file, not a folder"
    assert file_problem(tmp_path / "f" / "out.json", "--json") == (
        f"{tmp_path / 'f' / 'out.json'}: --json lies under {tmp_path / 'f'}, which is a file, not a folder")


@pytest.fixture
def locked(tmp_path):
    """A folder this process may read but not write in (skipped as root, who may write anywhere)."""
    if not hasattr(os, "geteuid") or os.geteuid() == 0:
        pytest.skip("root may write anywhere")
    folder = tmp_path / "locked"
    folder.mkdir(mode=0o500)
    return folder


def test_file_problem_names_an_unwritable_folder(locked):
    assert file_problem(locked / "a" / "out.json", "--out") == (
        f"{locked / 'a' / 'out.json'}: --out cannot be written ({locked}: permission denied)")


def test_make_folder_gives_the_systems_reason(locked):
    with pytest.raises(DepthnerfError, match=r"cannot create --out \(Permission denied\)"):
        make_folder(locked / "run", "--out")


def test_an_atomic_write_under_a_file_names_both(tmp_path):
    (tmp_path / "f").write_text("x")
    for write in (lambda p: write_text_atomic(p, "t"), lambda p: write_json_atomic(p, {})):
        with pytest.raises(DepthnerfError) as err:  # was mkdir's "[Errno 17] File exists: 'f'"
            write(tmp_path / "f" / "sub" / "out.json")
        assert str(err.value) == (f"{tmp_path / 'f' / 'sub' / 'out.json'}: cannot be written there: {tmp_path / 'f'} "
                                  "is a file, not a folder")


def test_an_atomic_write_that_fails_leaves_no_temporary_file(tmp_path, monkeypatch):
    """A rename that fails (a full disk, a folder in the way) raises and takes its temporary sibling with it."""
    def refuse(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("depthnerf.files.os.replace", refuse)
    for write in (lambda p: write_text_atomic(p, "t"), lambda p: write_json_atomic(p, {}),
                  lambda p: write_bytes_atomic(p, b"b")):
        with pytest.raises(OSError, match="No space left"):
            write(tmp_path / "out")
        assert list(tmp_path.iterdir()) == []
