"""Named tensors read from a weights file, checked before they go into a module: every value finite, every key and
shape the module's. One mechanism for the pixelNeRF checkpoints (:mod:`depthnerf.pretrained.weights`) and the
bundled depth net (:mod:`depthnerf.depth.bundled`); each mismatch is one :class:`DepthnerfError` line naming the
file. :func:`read_state_dict` reads the state dicts other code wrote (ImageNet trunks, LPIPS, pixelNeRF's own
weights). :func:`safetensors_bytes` writes them, the same bytes in every process. A neutral module: any stage may
use it."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import torch
from safetensors.torch import save

from depthnerf.errors import DepthnerfError


def check_finite(tensors: dict[str, torch.Tensor], path: Path, why: str) -> None:
    """One line naming ``path`` and the first tensor that holds NaN or inf, ending with ``why`` (what that means
    for this kind of file)."""
    for name, tensor in tensors.items():
        bad = int((~torch.isfinite(tensor)).sum()) if tensor.is_floating_point() else 0
        if bad:
            raise DepthnerfError(f"{path}: tensor {name} holds {bad} non-finite values (NaN or inf): {why}")


def load_state_strict(module: torch.nn.Module, tensors: dict[str, torch.Tensor], path: Path,
                      mismatch: str = "checkpoint does not match the model config") -> None:
    """Load weights with every key, shape and kind of dtype (floating or not) checked; a mismatch is one line naming
    the file, ``mismatch`` (what does not fit what), then the missing, unexpected, mis-shaped and mis-typed
    tensors. Floating tensors of another precision (fp16 files) are cast."""
    own = module.state_dict()
    missing = sorted(set(own) - set(tensors))
    unexpected = sorted(set(tensors) - set(own))
    shapes = [k for k in own if k in tensors and own[k].shape != tensors[k].shape]
    kinds = [k for k in own if k in tensors and own[k].is_floating_point() != tensors[k].is_floating_point()]
    if missing or unexpected or shapes or kinds:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)} tensors (e.g. {missing[0]})")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)} tensors (e.g. {unexpected[0]})")
        if shapes:
            k = shapes[0]
            parts.append(f"shape mismatch for {k}: file {tuple(tensors[k].shape)} vs model {tuple(own[k].shape)}")
        if kinds:  # a float weight stored as integers (truncated) or a counter stored as a float
            k = kinds[0]
            parts.append(f"dtype mismatch for {k}: file {tensors[k].dtype} vs model {own[k].dtype}")
        raise DepthnerfError(f"{path}: {mismatch}: {'; '.join(parts)}")
    module.load_state_dict({k: v.to(own[k].dtype) for k, v in tensors.items()}, strict=True)


def read_state_dict(path: str | Path, kind: str) -> dict[str, torch.Tensor]:
    """The flat state dict of tensors in ``path``: ``.safetensors``, else ``torch.load(weights_only=True)`` (never
    unpickled). ``kind`` names what the file should hold (e.g. "LPIPS weights") in the one error line that names the
    file when it is missing, unreadable or not a non-empty state dict of tensors."""
    path = Path(path)
    if not path.is_file():
        raise DepthnerfError(f"{path}: {kind} not found")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - any reader failure is a bad file
        first = str(err).strip().splitlines()[0] if str(err).strip() else ""
        raise DepthnerfError(f"{path}: cannot read {kind} ({type(err).__name__}: {first})") from None
    if not isinstance(state, dict) or not state or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise DepthnerfError(f"{path}: not a state dict of tensors (expected {kind})")
    return dict(state)


def safetensors_bytes(tensors: dict[str, torch.Tensor], metadata: dict[str, str] | None = None) -> bytes:
    """A safetensors file of ``tensors`` and ``metadata``, the same bytes for the same content in every process.

    ``safetensors.torch.save`` writes the metadata map in the order of a hash map seeded per process, so two runs
    of one export give files with equal content and different sha256s. The header it wrote (8-byte little-endian
    length, then JSON padded with spaces to a multiple of 8) is written again with the metadata keys sorted; the
    tensor entries and the data after the header are kept as they are (their offsets count from the data's
    start)."""
    raw = save(tensors, metadata=metadata)
    size = struct.unpack("<Q", raw[:8])[0]
    header = json.loads(raw[8:8 + size])
    if "__metadata__" in header:
        header = {"__metadata__": dict(sorted(header["__metadata__"].items())),
                  **{k: v for k, v in header.items() if k != "__metadata__"}}
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    return struct.pack("<Q", len(text)) + text + raw[8 + size:]
