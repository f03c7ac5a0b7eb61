"""Model weights files: safetensors tensors + JSON metadata, written atomically, loaded strictly.

Metadata of a weights file: ``format`` (:data:`FORMAT`), ``config`` (the model config JSON), ``step``,
``inference_spec`` (:mod:`depthnerf.pretrained.spec`) and, from training, ``train_config`` (provenance); a file
may also carry a facing head (:mod:`depthnerf.model.facing_head`: ``facing_head.*`` tensors and ``facing_head``
metadata). Nothing here unpickles.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from depthnerf.errors import DepthnerfError
from depthnerf.files import write_bytes_atomic
from depthnerf.model.facing_head import PREFIX as HEAD_PREFIX
from depthnerf.model.facing_head import FacingHead, head_tensors
from depthnerf.state_dicts import check_finite, safetensors_bytes

FORMAT = "depthnerf-checkpoint-1"
"""Format tag stored in every weights file's metadata."""


def save_weights(path: Path, module: torch.nn.Module, config: dict[str, Any], step: int = 0,
                 dtype: torch.dtype | None = None, extra: dict[str, str] | None = None) -> None:
    """Write ``module``'s state dict as safetensors with its model config in the metadata (atomically)."""
    tensors = {k: (v.to(dtype) if dtype is not None and v.is_floating_point() else v).detach().contiguous().cpu()
               for k, v in module.state_dict().items()}
    meta = {"format": FORMAT, "config": json.dumps(config, sort_keys=True), "step": str(step), **(extra or {})}
    write_bytes_atomic(Path(path), safetensors_bytes(tensors, metadata=meta))


def save_with_head(source: Path, head: FacingHead, out: Path) -> None:
    """Write ``source``'s weights file to ``out`` (atomically; ``out`` may be ``source``) with ``head`` as its
    facing head, replacing any it had; tensors and other metadata unchanged."""
    tensors, meta = read_weights(source)
    own, own_meta = head_tensors(head)
    tensors = {**{k: v for k, v in tensors.items() if not k.startswith(HEAD_PREFIX)}, **own}
    write_bytes_atomic(Path(out), safetensors_bytes(tensors, metadata={**meta, **own_meta}))


def read_weights(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Load a weights file written by :func:`save_weights`: ``(tensors, metadata)``; errors name the file (also
    for NaN or inf values, which a damaged file or a diverged run leaves and which would render black images)."""
    path = Path(path)
    if not path.is_file():
        raise DepthnerfError(f"{path}: checkpoint weights file not found")
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
        tensors = load_file(str(path))
    except (SafetensorError, OSError, ValueError) as err:
        raise DepthnerfError(f"{path}: not a readable safetensors checkpoint ({err})") from None
    if meta.get("format") != FORMAT:
        raise DepthnerfError(f"{path}: not a depthnerf checkpoint (format {meta.get('format')!r}, expected {FORMAT})")
    check_finite(tensors, path, "the file is damaged, or the run that wrote it diverged")
    return tensors, meta


def checkpoint_config(meta: dict[str, str], path: Path) -> dict[str, Any]:
    """The model config dict stored in a checkpoint's metadata."""
    try:
        return json.loads(meta["config"])
    except (KeyError, json.JSONDecodeError):
        raise DepthnerfError(f"{path}: checkpoint metadata has no valid model config") from None


def latest_checkpoint(ckpt_root: Path) -> Path | None:
    """The newest complete checkpoint directory, or None when there is none.

    That is the one ``latest`` names, or a newer ``step_*`` folder if a process was killed between renaming it
    into place (it is complete by then) and updating the pointer.
    """
    ckpt_root = Path(ckpt_root)
    pointer = ckpt_root / "latest"
    named = None
    complete = sorted(p for p in ckpt_root.glob("step_*") if (p / "state.json").is_file())
    newest = complete[-1] if complete else None
    if pointer.is_file():
        fix = f"; delete it to use the newest complete one, {newest.name}" if newest is not None else ""
        try:
            text = pointer.read_bytes().decode("utf-8").strip()
        except UnicodeDecodeError:
            raise DepthnerfError(f"{pointer}: not a text file naming a checkpoint folder (corrupt pointer){fix}") from None
        named = ckpt_root / text
        if not text or "/" in text or not (named / "state.json").is_file():
            raise DepthnerfError(f"{pointer}: names {text!r}, which is not a complete checkpoint in {ckpt_root}{fix}")
    if named is None or (newest is not None and newest.name > named.name):
        return newest
    return named


