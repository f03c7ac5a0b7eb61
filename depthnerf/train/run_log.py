"""A run folder's logs: ``metrics.jsonl`` (one JSON object per logged step), TensorBoard events and
``launches.jsonl`` (one JSON object per start or resume of the run: the step it started from, the world size =
number of torchrun ranks, the device, whether ``--deterministic`` was on and the time); the run's JSON records as a
resume reads them (:func:`read_run_record`); and the run folder's guards: :func:`check_run_dir` (a new run never
overwrites a ``config.json`` that is not a run's) and :func:`run_lock` (one process trains a run at a time).

On resume from step ``s`` every ``metrics.jsonl`` line with ``step > s`` (written by the interrupted process after
its last checkpoint) is dropped and TensorBoard is opened with ``purge_step = s + 1`` (TensorBoard hides the events
of steps ``>= purge_step``), so the logged curves of a resumed run are exactly those of an uninterrupted one. When
the checkpoint's validation of step ``s`` is still due (a stop signal came first), a validation line of step ``s`` is
dropped too (an earlier resume's, killed before it recorded that validation in the checkpoint).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from depthnerf.errors import DepthnerfError
from depthnerf.files import folder_problem, make_folder, write_text_atomic

try:
    import fcntl
except ImportError:  # not a POSIX system: no lock (run_lock then guards nothing)
    fcntl = None

LOCK_WAIT_S = 120.0
"""How long :func:`run_lock` waits for a held lock before it gives up (an NFS lease after a node crash: 90 s)."""
RUN_CONFIG_KEYS = frozenset({"preset", "data", "model", "schedule"})
"""Keys every run's ``config.json`` holds (how :func:`check_run_dir` tells a run's config from another file)."""


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


class RunLog:
    """Writer for ``RUN_DIR/metrics.jsonl`` and ``RUN_DIR/tb`` (rank 0 only)."""

    def __init__(self, run_dir: Path, start_step: int, tensorboard: bool = True, validation_due: bool = False) -> None:
        self.path = Path(run_dir) / "metrics.jsonl"
        self._truncate(start_step, validation_due)
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            # the step of the checkpoint was logged before it was written: only later events are the interrupted run's
            # (from step 0 too: a run killed before its first checkpoint starts again, its events are all stale)
            self.writer = SummaryWriter(str(Path(run_dir) / "tb"), purge_step=start_step + 1)

    def _truncate(self, start_step: int, validation_due: bool) -> None:
        if not self.path.exists():
            return
        keep = []
        for line in self.path.read_text().splitlines():
            try:
                record = json.loads(line)
                step = record.get("step", 0)
                if step < start_step or (step == start_step and not (validation_due and "val_psnr" in record)):
                    keep.append(line)
            except json.JSONDecodeError:
                break  # a line cut by a kill: everything after it is also after the checkpoint
        write_text_atomic(self.path, "".join(k + "\n" for k in keep))

    def log(self, step: int, values: dict[str, float], prefix: str = "train") -> None:
        """Append one JSON line and the matching TensorBoard scalars."""
        try:
            with open(self.path, "a") as f:
                f.write(json.dumps({"step": step, **{k: _clean(v) for k, v in values.items()}}) + "\n")
        except OSError as err:  # the run folder moved or deleted under the run, a full disk
            raise DepthnerfError(f"{self.path}: cannot append the step-{step} metrics ({err.strerror or err}); was "
                                 "the run folder moved or deleted while training?") from None
        if self.writer is not None:
            for key, value in values.items():
                if isinstance(value, int | float) and math.isfinite(value):
                    self.writer.add_scalar(f"{prefix}/{key}", value, step)

    def images(self, step: int, images: dict[str, np.ndarray]) -> None:
        """TensorBoard images (``H x W x 3`` or ``H x W`` arrays in [0, 1])."""
        if self.writer is None:
            return
        for name, img in images.items():
            arr = np.asarray(img, dtype=np.float32)
            if arr.ndim == 2:
                arr = np.repeat(arr[..., None], 3, axis=-1)
            self.writer.add_image(f"val/{name}", np.clip(arr, 0, 1), step, dataformats="HWC")

    def close(self) -> None:
        if self.writer is not None:
            self.writer.flush()
            self.writer.close()


def read_metrics(run_dir: Path) -> list[dict[str, Any]]:
    """All JSON lines of a run's ``metrics.jsonl``."""
    path = Path(run_dir) / "metrics.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []


def record_launch(run_dir: Path, start_step: int, world_size: int, device: str,
                  deterministic: bool = False) -> str | None:
    """Append this start of the run to ``RUN_DIR/launches.jsonl``; returns one line of notes when a resume is not
    bit for bit the run it continues: another world size than the previous launch (the global batch is the same;
    results agree within float rounding), or a CUDA resume without the ``--deterministic`` the previous launch had
    (CUDA's default kernels accumulate in a varying order); else None."""
    path = Path(run_dir) / "launches.jsonl"
    launches = read_launches(run_dir)
    previous = launches[-1] if launches and isinstance(launches[-1], dict) else {}
    if path.exists() and not path.read_text().endswith("\n") and path.stat().st_size:
        with open(path, "a") as f:
            f.write("\n")  # after a line cut by a kill
    entry = {"start_step": start_step, "world_size": world_size, "device": device, "deterministic": deterministic,
             "time": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    with open(path, "a") as f:
        f.write(json.dumps(entry) + "\n")
    notes = []
    old = previous.get("world_size")
    if start_step > 0 and old is not None and old != world_size:
        notes.append(f"resuming with world size {world_size} (the run's previous launch had {old}): the same global "
                     "batch, equal to the earlier launch within float rounding, not bit for bit")
    if start_step > 0 and previous.get("deterministic") and not deterministic and device.startswith("cuda"):
        notes.append("resuming without --deterministic (the run's previous launch had it): on CUDA the steps from "
                     "here match the uninterrupted run within float rounding, not bit for bit; add --deterministic "
                     "to keep the resume exact")
    return f"note: {'; '.join(notes)}" if notes else None


def read_launches(run_dir: Path) -> list[dict[str, Any]]:
    """All JSON lines of a run's ``launches.jsonl``."""
    path = Path(run_dir) / "launches.jsonl"
    out = []
    for line in path.read_text().splitlines() if path.exists() else []:
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue  # a line cut by a kill
    return out


def read_run_record(path: Path) -> dict[str, Any] | None:
    """A run's JSON record (``prior.json``, ``data_card.json``), None when the run has none (written before the file
    existed); a file that is there but unreadable or not a JSON object is one line naming it, never taken as absent
    (the resume checks the record feeds would be skipped)."""
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as err:
        raise DepthnerfError(f"{path}: unreadable run record ({err}); restore it to resume the run") from None
    if not isinstance(record, dict):
        raise DepthnerfError(f"{path}: not a run record (a JSON object); restore it to resume the run")
    return record


def check_run_dir(run_dir: Path, has_checkpoint: bool) -> None:
    """Refuse a ``--out`` that is a file or lies under one, holds a ``checkpoints`` file, or (for a run without a
    checkpoint of its own) holds a ``config.json`` that is not a depthnerf run's: training would overwrite it. Other
    files (a job's log redirected into the folder, notes) are left alone and allowed: training writes none of their
    names."""
    run_dir = Path(run_dir)
    problem = folder_problem(run_dir, "--out")
    if problem is not None:
        raise DepthnerfError(f"{problem}; choose another --out")
    if (run_dir / "checkpoints").exists() and not (run_dir / "checkpoints").is_dir():
        raise DepthnerfError(f"{run_dir / 'checkpoints'}: is a file, not a run's checkpoints folder; choose another "
                             "--out")
    config = run_dir / "config.json"
    if has_checkpoint or not config.exists():
        return
    try:
        data = json.loads(config.read_text())
    except (OSError, ValueError):
        data = None
    if not (isinstance(data, dict) and RUN_CONFIG_KEYS <= set(data)):
        raise DepthnerfError(f"{config}: not a depthnerf run's config, and a run in {run_dir} would overwrite it; "
                             "choose another --out")


@contextlib.contextmanager
def run_lock(run_dir: Path, wait_s: float | None = None) -> Iterator[None]:
    """Hold ``RUN_DIR/.lock`` (an advisory ``flock``, released when the process ends, however it ends) while a
    process trains the run; a second process on the same run (say, a job launched again while the first still
    runs) stops with one line instead of interleaving its steps with the first's. It first waits up to ``wait_s``
    (default :data:`LOCK_WAIT_S`) for the lock, saying so on stderr: a shared file system may hold a crashed node's
    lock until its lease ends, and a requeued job should not fail on that. SIGTERM or Ctrl+C during the wait ends
    the process with one line (it has written nothing to the run yet) and the signal's exit status."""
    run_dir = make_folder(Path(run_dir), "--out")
    if fcntl is None:
        yield
        return
    fd = os.open(run_dir / ".lock", os.O_RDWR | os.O_CREAT, 0o644)
    wait = LOCK_WAIT_S if wait_s is None else wait_s
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            _wait_for_lock(fd, run_dir, wait)
        except OSError:  # a file system without flock (e.g. Lustre mounted without it): train unguarded
            pass
        yield
    finally:
        os.close(fd)


class _StopWhileWaiting(Exception):
    """A stop signal arrived while :func:`_wait_for_lock` waited."""


def _wait_for_lock(fd: int, run_dir: Path, wait_s: float) -> None:
    """Take the held lock on ``fd`` once its holder lets go, polling once a second for ``wait_s`` seconds (a
    :class:`DepthnerfError` after that); a stop signal meanwhile exits (:func:`run_lock`)."""
    if wait_s > 0:
        print(f"{run_dir}: another process holds this run's lock; waiting up to {wait_s:.0f} s for it",
              file=sys.stderr, flush=True)

    def stop(signum: int, frame: object) -> None:
        raise _StopWhileWaiting(signum)
    main_thread = threading.current_thread() is threading.main_thread()
    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT)} if main_thread else {}
    deadline = time.monotonic() + wait_s
    try:
        while True:
            if time.monotonic() >= deadline:
                raise DepthnerfError(f"{run_dir}: another process is training this run; wait for it to end (or "
                                     "stop it) before resuming")
            time.sleep(min(1.0, max(deadline - time.monotonic(), 0.0)))
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                continue
    except _StopWhileWaiting as stopped:
        signum = stopped.args[0]
        print(f"{run_dir}: stopped by {signal.Signals(signum).name} while waiting for the run's lock; this process "
              "wrote nothing to the run", file=sys.stderr, flush=True)
        raise SystemExit(128 + signum) from None
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
