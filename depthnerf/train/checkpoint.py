"""Checkpoints you can trust: safetensors weights, atomic writes, strict loading, exact-resume state.

Layout of a run's ``checkpoints/`` folder::

    step_00001000/            one checkpoint (a directory, renamed into place atomically)
        model.safetensors     model weights; metadata ``{"format", "config", "step"}`` (config = model config JSON)
        optimizer.safetensors optimizer tensors (Adam moments, per-parameter step counts)
        state.json            step, optimizer hyper-parameters, training counters, metrics at save time
    best/                     copy of the checkpoint with the best validation PSNR (same layout)
    latest                    text file naming the newest complete checkpoint directory

A checkpoint directory only appears under its final name once every file in it is written and fsynced, so a
process killed at any moment leaves either the previous state or the new one, never a half-written checkpoint.
A write that fails (a full disk) removes its temporary folder and is one :class:`DepthnerfError` line. A kill
between a checkpoint and its copy to ``best/`` is mended when the run resumes (:func:`restore_best`, from the
``best_step`` the state records). Nothing here unpickles: tensors go through safetensors, everything else through
JSON.

Crash test hook: with ``DEPTHNERF_CRASH_AT=STAGE@STEP`` in the environment the process SIGKILLs itself at
``STAGE`` of the checkpoint write of step ``STEP`` (one of :data:`CRASH_STAGES`), so a test can kill training at
every point of a write deterministically instead of racing a timer (``tests/test_train.py``). The loop adds two
points, ``step`` (after the optimiser step) and ``validation`` (as validation starts), and
``DEPTHNERF_CRASH_AT=sigterm-STAGE@STEP`` / ``sigint-STAGE@STEP`` sends the process SIGTERM / SIGINT there instead
(the clean stop of :mod:`depthnerf.train.stop`; the hook: :mod:`depthnerf.crash_hook`).
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save

from depthnerf.config_io import to_dict
from depthnerf.crash_hook import crash_point
from depthnerf.errors import DepthnerfError
from depthnerf.files import write_bytes_atomic, write_text_atomic
from depthnerf.pretrained.spec import SPEC_KEY, model_config_from_dict
from depthnerf.pretrained.weights import (  # noqa: F401 - re-exported for the run-folder code
    FORMAT,
    checkpoint_config,
    latest_checkpoint,
    read_weights,
    save_weights,
)
from depthnerf.state_dicts import load_state_strict

CHECKPOINT_FILES = ("model.safetensors", "optimizer.safetensors", "state.json")
"""The files of a complete checkpoint folder."""
RUNTIME_KEYS = ("fused", "foreach", "capturable")
"""Optimizer settings of how the update runs on a device, not what it computes: a loaded optimizer keeps the ones it
was built with (a CUDA run's fused Adam is not carried into a CPU resume, nor its absence into a CUDA one)."""
CRASH_STAGES = ("weights", "optimizer", "state", "renamed", "latest", "pruned", "best-copied", "best-moved")
"""Points of a checkpoint write where ``DEPTHNERF_CRASH_AT`` can kill the process: after the weights / optimizer /
state files of the temporary folder are written, after the folder is renamed into place, after the ``latest``
pointer is updated, after old checkpoints are pruned; for ``best``: after its temporary copy, after the old
``best`` was moved aside (before the new one takes its place). The hook itself: :mod:`depthnerf.crash_hook`."""



def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _optimizer_to_files(opt: torch.optim.Optimizer) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    sd = opt.state_dict()
    tensors: dict[str, torch.Tensor] = {}
    scalars: dict[str, dict[str, Any]] = {}
    for pid, st in sd["state"].items():
        for name, value in st.items():
            if torch.is_tensor(value):
                tensors[f"{pid}.{name}"] = value.detach().contiguous().cpu()
            else:
                scalars.setdefault(str(pid), {})[name] = value
    return tensors, {"param_groups": sd["param_groups"], "scalars": scalars}


def _optimizer_from_files(opt: torch.optim.Optimizer, tensors: dict[str, torch.Tensor], info: dict[str, Any]) -> None:
    state: dict[int, dict[str, Any]] = {}
    for key, value in tensors.items():
        pid, name = key.split(".", 1)
        state.setdefault(int(pid), {})[name] = value
    for pid, st in info.get("scalars", {}).items():
        state.setdefault(int(pid), {}).update(st)
    # this device's settings before the load: torch places each parameter's step count by them as it loads
    groups = [{**saved, **{k: group[k] for k in RUNTIME_KEYS if k in group}}
              for saved, group in zip(info["param_groups"], opt.param_groups, strict=False)]
    opt.load_state_dict({"state": state, "param_groups": groups})
    # Files hold contiguous tensors; a channels-last parameter's moments must have its strides again (CUDA's fused
    # Adam refuses a layout mismatch). Same values, bit for bit.
    for param, st in opt.state.items():
        for name, value in st.items():
            if torch.is_tensor(value) and value.shape == param.shape and value.stride() != param.stride():
                st[name] = torch.empty_like(param, dtype=value.dtype).copy_(value)


@dataclass(frozen=True)
class TrainingState:
    """What a resumed run needs besides weights: all batches and noise derive from (seed, step)."""

    step: int
    """Number of optimisation steps completed."""
    best_psnr: float
    """Best validation PSNR so far (-inf before the first validation)."""
    world_size: int = 1
    """Processes (torchrun ranks) of the run that wrote the checkpoint (1 in state files that predate it)."""
    best_step: int | None = None
    """The step whose checkpoint scored ``best_psnr`` (what ``best/`` holds; None: no validation yet, or a state
    file that predates it)."""
    validation_due: bool = False
    """The step was a validation step whose validation did not run (a stop signal came before it ended): a resume
    runs it before the next step (False in state files that predate it)."""


def save_checkpoint(ckpt_root: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
                    model_config: dict[str, Any], state: TrainingState, keep_last: int = 3,
                    train_config: dict[str, Any] | None = None, spec_json: str | None = None) -> Path:
    """Write ``ckpt_root/step_XXXXXXXX`` atomically, point ``latest`` at it, prune older ones (keep ``keep_last``).

    ``train_config`` (the run's whole config) goes into the weights' metadata too, so a weights file alone says
    how to use it (z-range, resolution, depth prior); ``spec_json`` is the run's inference spec
    (:mod:`depthnerf.pretrained.spec`), what evaluation and reconstruction read.
    """
    ckpt_root = Path(ckpt_root)
    ckpt_root.mkdir(parents=True, exist_ok=True)
    name = f"step_{state.step:08d}"
    tmp = ckpt_root / f".{name}.{os.getpid()}.tmp"
    final = ckpt_root / name
    try:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        _write_checkpoint_files(tmp, model, optimizer, model_config, state, train_config, spec_json)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
        _fsync_dir(ckpt_root)
        crash_point("renamed", state.step)
        write_text_atomic(ckpt_root / "latest", name + "\n")
    except (OSError, SafetensorError) as err:  # e.g. a full disk: the run keeps its previous checkpoint
        shutil.rmtree(tmp, ignore_errors=True)
        raise DepthnerfError(f"{final}: could not write the checkpoint ({err}); the run keeps its last complete "
                             "checkpoint: make room (or mend the folder) and continue it with --resume") from None
    except BaseException:  # a second Ctrl+C: no temporary folder left behind
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    crash_point("latest", state.step)
    prune(ckpt_root, keep_last)
    crash_point("pruned", state.step)
    return final


def prune(ckpt_root: Path, keep_last: int) -> None:
    """Keep the newest ``keep_last`` complete checkpoints of ``ckpt_root`` (all of them when 0) and remove every
    step folder older than those, complete or not. A folder an earlier kill left half-deleted is not counted among
    those kept; it goes once its step is that old. Each folder is renamed to ``.step_XXXXXXXX.PID.old`` before it is
    deleted, so a kill during a deletion leaves a temporary name (removed by the resume, :func:`restore_best`), not
    a half-deleted step folder."""
    folders = sorted(p for p in Path(ckpt_root).glob("step_*") if p.is_dir())
    complete = [p for p in folders if all((p / name).is_file() for name in CHECKPOINT_FILES)]
    if keep_last <= 0 or not complete:
        return
    oldest_kept = complete[-keep_last:][0]
    for old in folders:
        if old >= oldest_kept:
            break
        trash = old.with_name(f".{old.name}.{os.getpid()}.old")
        shutil.rmtree(trash, ignore_errors=True)  # a killed process's, under this id: a rename onto it would fail
        try:
            os.replace(old, trash)
        except OSError:  # cannot rename it (permissions): delete it where it is
            trash = old
        shutil.rmtree(trash, ignore_errors=True)


def _write_checkpoint_files(tmp: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
                            model_config: dict[str, Any], state: TrainingState, train_config: dict[str, Any] | None,
                            spec_json: str | None) -> None:
    """The files of one checkpoint into its temporary folder ``tmp`` (each written atomically and fsynced)."""
    extra = {"train_config": json.dumps(train_config, sort_keys=True)} if train_config is not None else {}
    if spec_json is not None:
        extra[SPEC_KEY] = spec_json
    save_weights(tmp / "model.safetensors", model, model_config, step=state.step, extra=extra)
    crash_point("weights", state.step)
    opt_tensors, opt_info = _optimizer_to_files(optimizer)
    write_bytes_atomic(tmp / "optimizer.safetensors", save(opt_tensors))
    crash_point("optimizer", state.step)
    write_text_atomic(tmp / "state.json", _state_json(state, opt_info))
    _fsync_dir(tmp)
    crash_point("state", state.step)


def _state_json(state: TrainingState, opt_info: dict[str, Any]) -> str:
    """``state.json``'s text: the state and the optimizer's hyper-parameters and scalars."""
    best = state.best_psnr if math.isfinite(state.best_psnr) else None  # strict JSON
    payload = {"step": state.step, "best_psnr": best, "best_step": state.best_step, "world_size": state.world_size,
               "validation_due": state.validation_due, "optimizer": opt_info}
    return json.dumps(payload, indent=1, allow_nan=False)


def rewrite_state(ckpt_dir: Path, state: TrainingState) -> None:
    """Replace the training state of the checkpoint ``ckpt_dir`` (of the same step; its weights and optimizer
    unchanged) by ``state``, in one atomic write of its ``state.json``: what a resume that ran the step's due
    validation records (its best PSNR and step, no validation due)."""
    where = Path(ckpt_dir) / "state.json"
    try:
        payload = json.loads(where.read_text())
        if int(payload["step"]) != state.step:
            raise ValueError(f"holds step {payload['step']}, not {state.step}")
        write_text_atomic(where, _state_json(state, payload["optimizer"]))
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise DepthnerfError(f"{where}: could not record the step's validation ({type(err).__name__}: {err}); "
                             "the run keeps its checkpoint: --resume validates the step again") from None


def last_step(ckpt_root: Path) -> int:
    """The step of the newest complete checkpoint in ``ckpt_root`` (:func:`latest_checkpoint`), what a resume
    continues from; 0 when there is none, or when its state file is unreadable (:func:`load_checkpoint` says so)."""
    latest = latest_checkpoint(ckpt_root) if Path(ckpt_root).is_dir() else None
    try:
        return int(json.loads((latest / "state.json").read_text())["step"]) if latest is not None else 0
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def restore_best(ckpt_root: Path, state: TrainingState) -> str | None:
    """On resume: remove the temporary folders a killed writer or pruning left, and when ``best/`` does not hold the
    state's ``best_step`` (a kill between that checkpoint and its copy, or during the copy) copy it there now;
    returns a one-line note when it did."""
    ckpt_root = Path(ckpt_root)
    for stray in [*ckpt_root.glob(".step_*.tmp"), *ckpt_root.glob(".step_*.old"), *ckpt_root.glob(".best.*.tmp")]:
        shutil.rmtree(stray, ignore_errors=True)
    source = ckpt_root / f"step_{state.best_step:08d}" if state.best_step is not None else None
    try:
        held = json.loads((ckpt_root / "best" / "state.json").read_text()).get("step")
    except (OSError, ValueError, AttributeError):
        held = None
    if source is None or held == state.best_step or not (source / "state.json").is_file():
        return None
    mark_best(ckpt_root, source)
    for stray in ckpt_root.glob(".best.*.old"):
        shutil.rmtree(stray, ignore_errors=True)
    return f"restored {ckpt_root / 'best'} from {source.name} (a kill had interrupted its copy)"


def mark_best(ckpt_root: Path, ckpt_dir: Path) -> None:
    """Make ``ckpt_root/best`` an atomic copy of ``ckpt_dir``."""
    tmp = ckpt_root / f".best.{os.getpid()}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(ckpt_dir, tmp)
    step = int(ckpt_dir.name.split("_")[-1]) if ckpt_dir.name.startswith("step_") else -1
    crash_point("best-copied", step)
    old = ckpt_root / f".best.{os.getpid()}.old"
    shutil.rmtree(old, ignore_errors=True)  # a killed process's, under this id: a rename onto it would fail
    if (ckpt_root / "best").exists():
        os.replace(ckpt_root / "best", old)
    crash_point("best-moved", step)
    os.replace(tmp, ckpt_root / "best")
    shutil.rmtree(old, ignore_errors=True)


def _with_defaults(stored: dict[str, Any], model: torch.nn.Module, ckpt_dir: Path) -> dict[str, Any]:
    """A stored :class:`PixelNeRFConfig` dict as the current code reads it, as inference reads it too
    (:func:`depthnerf.pretrained.spec.model_config_from_dict`): fields added since the checkpoint was written take
    their defaults, which reproduce the behaviour it was trained with, and the legacy ``encoder.use_depth`` is
    checked against the model and dropped. Anything that is not such a config is compared as stored."""
    depth_aware = getattr(model, "depth_aware", None)
    if not isinstance(depth_aware, bool):
        return stored
    try:
        return json.loads(json.dumps(to_dict(model_config_from_dict(stored, depth_aware, str(ckpt_dir)))))
    except DepthnerfError:
        return stored


def load_checkpoint(ckpt_dir: Path, model: torch.nn.Module, optimizer: torch.optim.Optimizer | None,
                    model_config: dict[str, Any]) -> TrainingState:
    """Restore weights (strictly, after checking the stored model config) and optimizer; return the state."""
    ckpt_dir = Path(ckpt_dir)
    tensors, meta = read_weights(ckpt_dir / "model.safetensors")
    stored = _with_defaults(checkpoint_config(meta, ckpt_dir / "model.safetensors"), model, ckpt_dir)
    if stored != json.loads(json.dumps(model_config)):
        diff = sorted(k for k in set(stored) | set(model_config) if stored.get(k) != model_config.get(k))
        raise DepthnerfError(f"{ckpt_dir}: checkpoint was trained with a different model config (differs in: "
                             f"{', '.join(diff)}); resume with the run's own config")
    load_state_strict(model, tensors, ckpt_dir / "model.safetensors")
    where = ckpt_dir / "state.json"
    try:
        payload = json.loads(where.read_text())
        best, best_step = payload["best_psnr"], payload.get("best_step")  # older files: an unused "extra" mapping
        state = TrainingState(step=int(payload["step"]), best_psnr=-math.inf if best is None else float(best),
                              world_size=int(payload.get("world_size", 1)),
                              best_step=None if best_step is None else int(best_step),
                              validation_due=bool(payload.get("validation_due", False)))
        opt_info = payload["optimizer"] if optimizer is not None else None
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:  # JSONDecodeError is a ValueError
        raise DepthnerfError(f"{where}: unreadable training state ({type(err).__name__}: {err})") from None
    if optimizer is not None:
        try:
            opt_tensors = load_file(str(ckpt_dir / "optimizer.safetensors"))
        except (SafetensorError, OSError) as err:
            raise DepthnerfError(f"{ckpt_dir / 'optimizer.safetensors'}: unreadable optimizer state ({err})") from None
        try:
            _optimizer_from_files(optimizer, opt_tensors, opt_info)
        except (ValueError, KeyError, TypeError, AttributeError) as err:
            raise DepthnerfError(f"{ckpt_dir}: optimizer state does not fit the model ({type(err).__name__}: "
                                 f"{err})") from None
    return state
