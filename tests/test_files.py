"""``depthnerf.files``: atomic writes and file hashes against hashlib and the file system."""

from __future__ import annotations

import hashlib
import json

from depthnerf.files import sha256_file, sha256_files, write_json_atomic, write_text_atomic


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
