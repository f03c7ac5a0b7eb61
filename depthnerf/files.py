"""Crash-safe file writes, output folders, content hashes and JSON-object reads shared by the data, depth-cache,
training and checkpoint code.

A write goes to a temporary file in the destination folder (so the rename stays on one file system), is flushed
and fsynced, then renamed over the destination with ``os.replace``: a reader sees the old file or the new one,
never a torn one, and a crash leaves at most a stray ``.NAME.PID.tmp`` file behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from depthnerf.errors import DepthnerfError


def temporary_sibling(path: Path) -> Path:
    """The temporary name used for an atomic write of ``path`` (hidden; unique per call, also across machines and
    containers whose processes share a file system and a process id)."""
    return path.with_name(f".{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")


def nearest_existing(path: Path) -> Path:
    """``path`` itself when it exists, else its nearest ancestor that does (the file system's root at worst)."""
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def _file_in_the_way(path: Path, what: str, existing: Path) -> str | None:
    """The line :func:`folder_problem` and :func:`file_problem` give when ``existing`` (``path`` or its nearest
    existing ancestor) is a file rather than a folder, naming ``path`` and ``what`` it is for; None when it is a
    folder."""
    if existing.is_dir():
        return None
    if existing == path:
        return f"{path}: {what} is a file, not a folder"
    return f"{path}: {what} lies under {existing}, which is a file, not a folder"


def folder_problem(path: Path, what: str) -> str | None:
    """Why ``path`` cannot be (or become) a folder, as one line naming it and ``what`` it is for (a flag such as
    ``--out``), or None. Looks only: the path itself or its nearest existing ancestor must be a folder."""
    path = Path(path)
    return _file_in_the_way(path, what, nearest_existing(path))


def file_problem(path: Path, what: str) -> str | None:
    """Why ``path`` cannot be written as a file, as one line naming it and ``what`` it is for (a flag such as
    ``--json``), or None. Looks only: ``path`` must not be a folder, and its nearest existing ancestor must be a
    writable folder (an atomic write creates a sibling file there, then renames it)."""
    path = Path(path)
    if path.is_dir():
        return f"{path}: {what} is a folder; name the file to write"
    existing = nearest_existing(path.parent)
    if (problem := _file_in_the_way(path, what, existing)) is not None:
        return problem
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{path}: {what} cannot be written ({existing}: permission denied)"
    return None


def make_folder(path: Path, what: str) -> Path:
    """Create ``path`` and its parents (``exist_ok``) as the folder for ``what``, or raise one line naming it: a file
    in the way (:func:`folder_problem`) or the system's reason (permission denied, read-only file system)."""
    path = Path(path)
    problem = folder_problem(path, what)
    if problem is not None:
        raise DepthnerfError(problem)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot create {what} ({err.strerror or err})") from None
    return path


def _make_parent(path: Path) -> None:
    """Create the folder ``path`` goes in; a file in the way is one line naming both, not ``mkdir``'s bare "File
    exists" or "Not a directory"."""
    existing = nearest_existing(path.parent)
    if not existing.is_dir():
        raise DepthnerfError(f"{path}: cannot be written there: {existing} is a file, not a folder")
    path.parent.mkdir(parents=True, exist_ok=True)


def write_text_atomic(path: Path, text: str) -> None:
    """:func:`write_bytes_atomic` of ``text`` in UTF-8."""
    write_bytes_atomic(path, text.encode("utf-8"))


def write_bytes_atomic(path: Path, data: bytes, mode: int = 0o644) -> None:
    """Write ``data`` to ``path`` atomically and durably (temporary sibling, fsync, rename) with permissions ``mode``.

    Binary files (safetensors weights and depth priors) are serialised to bytes first
    (``safetensors.torch.save``) and written through here, like the text writers.
    """
    path = Path(path)
    _make_parent(path)
    tmp = temporary_sibling(path)
    try:
        with open(tmp, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def read_json_object(path: Path, what: str) -> dict[str, Any]:
    """The JSON object in ``path``; a file that cannot be read, is not JSON or holds no object is a
    :class:`~depthnerf.errors.DepthnerfError` naming the file and ``what`` it should be."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise DepthnerfError(f"{path}: unreadable {what} ({err})") from None
    if not isinstance(data, dict):
        raise DepthnerfError(f"{path}: unreadable {what} (a JSON object was expected, got {type(data).__name__})")
    return data


def write_json_atomic(path: Path, payload: dict[str, Any]) -> None:
    """:func:`write_text_atomic` of ``payload`` as indented JSON with sorted keys and a final newline."""
    write_text_atomic(path, json.dumps(payload, indent=2, sort_keys=True) + "\n")


def sha256_files(paths: Iterable[Path], *, names: bool = True) -> str:
    """SHA-256 over the given files in order (each base name first, NUL-terminated, when ``names``), streamed."""
    digest = hashlib.sha256()
    for path in paths:
        path = Path(path)
        if names:
            digest.update(path.name.encode() + b"\0")
        with open(path, "rb") as handle:
            while chunk := handle.read(1 << 20):
                digest.update(chunk)
    return digest.hexdigest()


def sha256_file(path: Path) -> str:
    """SHA-256 of one file's bytes (``sha256sum``'s digest)."""
    return sha256_files([path], names=False)
