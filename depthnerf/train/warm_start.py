"""Warm start: a new run's network initialised from another checkpoint's weights (``TrainConfig.init_from``).

Only the weights are taken: the step, the optimiser's moments and the learning-rate schedule start fresh, so a
warm-started run is "N more steps from that model" with its own schedule (e.g. a cosine decay that anneals a
shipped model). The source's model config and prior must equal the run's: a different width, mirror or prior
would load into a different function (or fail on shapes), so any difference is an error naming the first one. One
difference is allowed because it adds to the network without changing its function: a source without
``global_features`` starts a run with them (:data:`ADDED_AT_ZERO`), the new linears starting at zero weights and
bias, so the run's first step starts from the source's function and the new term grows from its gradient.
Settings of training alone (:data:`TRAINING_ONLY`: whose statistics the encoder normalises with) may differ too.
A source trained on another category than the run's data is one warning line, not an error: a cross-category warm
start may be deliberate.

Steps in all. A chain of warm starts is recorded as the steps behind each source *in all*
(:attr:`WarmStart.total_steps`, :func:`steps_in_all`): the source's ``total_steps`` metadata (written by
``scripts/export_checkpoint.py``), else the ``total_steps`` of the card beside it that describes these very weights,
else, for a checkpoint inside a run folder (``RUN/checkpoints/NAME/model.safetensors``, what ``--init-from RUN``
resolves to), its own steps plus the ``total_steps`` of that run's ``init_from.json``, else its own steps (a model
trained from scratch, or a chain that predates the field).
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import torch

from depthnerf.config_io import differences, to_dict
from depthnerf.errors import DepthnerfError, UsageWarning
from depthnerf.files import sha256_file
from depthnerf.model.config import PixelNeRFConfig
from depthnerf.model.facing_head import PREFIX as HEAD_PREFIX
from depthnerf.pretrained.load import resolve_checkpoint
from depthnerf.pretrained.spec import spec_from_metadata
from depthnerf.pretrained.weights import read_weights
from depthnerf.state_dicts import load_state_strict

__all__ = ["ADDED_AT_ZERO", "TRAINING_ONLY", "WarmStart", "steps_in_all", "warm_start"]

ADDED_AT_ZERO: dict[str, str] = {"global_features": "lin_global"}
"""Model switches a warm start may turn on (source off, run on) -> the name of the modules they add, which start at
zero: each adds a term to a hidden layer, so at zero the network computes the source's function."""
TRAINING_ONLY: frozenset[str] = frozenset({"encoder.norm_stats"})
"""Model settings that change only how training computes (not the weights or the function evaluation computes),
so a warm start may change them either way."""


@dataclass(frozen=True)
class WarmStart:
    """Where a warm-started run's weights came from (written to the run's ``init_from.json``)."""

    source: str
    """``init_from`` as configured (a shipped name or a path)."""
    path: str
    """The weights file it resolved to."""
    sha256: str
    """SHA-256 of that file."""
    step: int
    """Training steps behind the source weights (its own run's)."""
    total_steps: int
    """Training steps behind the source weights in all, its own warm starts' included (module docstring)."""

    def to_json(self) -> str:
        return json.dumps(self.__dict__, indent=1) + "\n"


def steps_in_all(path: str | Path, meta: dict[str, str], sha256: str) -> int:
    """The training steps behind the weights file ``path`` (metadata ``meta``, SHA-256 ``sha256``) in all (module
    docstring)."""
    step = int(meta.get("step", 0))
    if "total_steps" in meta:
        return int(meta["total_steps"])
    card = Path(path).with_suffix(".json")
    try:
        found = json.loads(card.read_text()) if card.is_file() else {}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        found = {}
    total = found.get("total_steps") if isinstance(found, dict) and found.get("sha256") == sha256 else None
    if isinstance(total, int) and total >= step:
        return total
    return step + _run_warm_start_steps(Path(path))


def _run_warm_start_steps(path: Path) -> int:
    """The steps in all behind the warm start of the run whose checkpoint ``path`` is (``RUN/checkpoints/NAME/
    model.safetensors``): its ``init_from.json``'s ``total_steps`` (else ``step``); 0 for a file outside a run
    folder or a run trained from scratch. A record that cannot be read is an error naming it: the count would be
    wrong without a word."""
    if path.parent.parent.name != "checkpoints":
        return 0
    record = path.parent.parent.parent / "init_from.json"
    if not record.is_file():
        return 0
    try:
        warm = json.loads(record.read_text())
        behind = warm.get("total_steps", warm.get("step"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
        behind = None
    if not isinstance(behind, int) or isinstance(behind, bool) or behind < 0:
        raise DepthnerfError(f"{record}: not a readable warm-start record (no step count); the steps behind "
                             f"{path} cannot be counted")
    return behind


def warm_start(model: torch.nn.Module, source: str, model_cfg: PixelNeRFConfig, depth_aware: bool,
               category: str | None = None) -> WarmStart:
    """Load ``source``'s weights into ``model`` (strictly) after checking that it is the same network; a source
    trained on another ``category`` than the run's data is warned of in one line (it may be deliberate)."""
    path = resolve_checkpoint(source)
    tensors, meta = read_weights(path)
    tensors = {k: v for k, v in tensors.items() if not k.startswith(HEAD_PREFIX)}  # a facing head is refitted
    spec = spec_from_metadata(meta, str(path))
    if category is not None and spec.category != category:
        warnings.warn(f"{path}: --init-from is a {spec.category} model, the run trains on {category} data; the "
                      f"warm start begins from another category's weights", UsageWarning, stacklevel=2)
    if spec.depth_aware != depth_aware:
        kind = {True: "depth-aware", False: "a baseline (no prior)"}
        raise DepthnerfError(f"{path}: --init-from is {kind[spec.depth_aware]}, the run is {kind[depth_aware]}; "
                             "choose a checkpoint with the run's --depth")
    differ = differences(to_dict(spec.model), to_dict(model_cfg))
    added = [key for key, (theirs, ours) in differ.items() if key in ADDED_AT_ZERO and not theirs and ours]
    for key in added + [key for key in differ if key in TRAINING_ONLY]:
        del differ[key]
    if differ:
        k, (theirs, ours) = next(iter(differ.items()))
        raise DepthnerfError(f"{path}: --init-from has model.{k} = {theirs!r}, the run {ours!r} "
                             f"({len(differ)} model setting(s) differ); train with the checkpoint's model config")
    if added:
        own = model.state_dict()
        names = tuple(f".{ADDED_AT_ZERO[key]}." for key in added)
        tensors = {**tensors, **{k: torch.zeros_like(t) for k, t in own.items() if any(n in k for n in names)}}
    load_state_strict(model, tensors, path)
    sha = sha256_file(path)
    return WarmStart(source=str(source), path=str(Path(path).resolve()), sha256=sha, step=int(meta.get("step", 0)),
                     total_steps=steps_in_all(path, meta, sha))
