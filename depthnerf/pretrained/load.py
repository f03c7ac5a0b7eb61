"""Loading a trained model from anything a user may call a checkpoint.

``--checkpoint`` (eval, reconstruct, the Python API) accepts, in this order:
1. a shipped checkpoint name (``depthnerf checkpoints`` lists them, e.g. ``cpu-cars-depth``): a file
   ``depthnerf/checkpoints/<name>.safetensors`` inside the package (a retired name, whose weights no longer ship
   but whose card stays in ``depthnerf/checkpoints/retired/``, is an error pointing to that card);
2. a ``.safetensors`` weights file written by training or by ``scripts/export_checkpoint.py``;
3. a checkpoint directory (``RUN/checkpoints/step_XXXXXXXX`` or ``.../best``);
4. a run directory: its ``checkpoints/best`` if validation ran, else its latest checkpoint;
5. a Hugging Face Hub file, ``hf://OWNER/REPO[/FILE][@REVISION]`` (:mod:`depthnerf.pretrained.hub`), fetched
   into the Hugging Face cache and then read as a local weights file.

The weights' metadata carries the inference spec (:mod:`depthnerf.pretrained.spec`; derived from the stored
model and training configs for checkpoints written before specs existed, and its framing derived here for specs
written before the framing was), so the model is rebuilt exactly and loaded strictly (a mismatch is an error
naming the file, never a partial load).
"""

from __future__ import annotations

import difflib
import json
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from depthnerf.data.synth.framing import FRAMINGS, checkpoint_framing
from depthnerf.depth.prior import portable_prior
from depthnerf.distributed import pick_device
from depthnerf.errors import DepthnerfError
from depthnerf.files import sha256_file
from depthnerf.model.facing_head import PREFIX as HEAD_PREFIX
from depthnerf.model.facing_head import FacingHead, check_encoder, head_from_tensors
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.pretrained.hub import fetch_hub_checkpoint, is_hub_reference
from depthnerf.pretrained.spec import InferenceSpec, spec_from_metadata
from depthnerf.pretrained.weights import latest_checkpoint, read_weights
from depthnerf.state_dicts import load_state_strict

SHIPPED_DIR = Path(__file__).resolve().parent.parent / "checkpoints"
"""Where the package's own checkpoints live."""
SPEC_FRAMING = "the checkpoint's inference spec"
"""``Pretrained.framing_origin`` of a checkpoint whose spec states its framing."""


RUN_MARKERS = ("launches.jsonl", "data_card.json")
"""Files ``depthnerf train`` writes into a run folder when it starts, before its first checkpoint."""


def shipped_checkpoints() -> dict[str, Path]:
    """Names and paths of the checkpoints shipped inside the package."""
    return {p.stem: p for p in sorted(SHIPPED_DIR.glob("*.safetensors"))}


def retired_checkpoints() -> dict[str, Path]:
    """Names and model cards of the checkpoints that shipped once and no longer do: ``SHIPPED_DIR/retired/<name>.md``
    (beside its ``.json``) says what replaced each one and gives the commands that rebuild it."""
    return {p.stem: p for p in sorted((SHIPPED_DIR / "retired").glob("*.md"))}


def resolve_checkpoint(checkpoint: str | Path) -> Path:
    """The weights file ``checkpoint`` names: a shipped name or a path (see the module docstring)."""
    shipped = shipped_checkpoints()
    if isinstance(checkpoint, str) and checkpoint in shipped:
        return shipped[checkpoint]
    if is_hub_reference(checkpoint):
        return fetch_hub_checkpoint(checkpoint)
    path = Path(checkpoint)
    if path.is_file():
        return path
    if (path / "model.safetensors").is_file():
        return path / "model.safetensors"
    ckpt_root = path / "checkpoints"
    if ckpt_root.is_dir():
        best = ckpt_root / "best"
        if (best / "model.safetensors").is_file():
            return best / "model.safetensors"
        latest = latest_checkpoint(ckpt_root)
        if best.exists():  # written whole by a rename, so a best/ without its weights was damaged afterwards
            instead = f"; delete it to use the latest checkpoint, {latest.name}" if latest is not None else ""
            raise DepthnerfError(f"{best}: best checkpoint without model.safetensors{instead}")
        if latest is not None:
            return latest / "model.safetensors"
        raise DepthnerfError(f"{path}: run folder has no complete checkpoint yet")
    if any((path / name).is_file() for name in RUN_MARKERS):  # a run stopped before its first checkpoint
        raise DepthnerfError(f"{path}: run folder has no checkpoint yet (no {ckpt_root.name}/ folder)")
    retired = retired_checkpoints()
    if isinstance(checkpoint, str) and checkpoint in retired:
        raise DepthnerfError(f"{checkpoint}: a retired checkpoint, no longer shipped with depthnerf; its card "
                             f"{retired[checkpoint]} names what replaced it and the commands that rebuild it")
    names = ", ".join(shipped) or "none shipped"
    close = difflib.get_close_matches(str(checkpoint), [*shipped, *retired], n=1)
    hint = f"; did you mean {close[0]}?" if close else ""
    raise DepthnerfError(f"{checkpoint}: not a checkpoint file, checkpoint folder, run folder, shipped name "
                         f"({names}) or Hub file (hf://OWNER/REPO){hint}")


@dataclass
class Pretrained:
    """A loaded model with everything needed to use it as it was trained."""

    model: PixelNeRF
    """The network, in eval mode."""
    spec: InferenceSpec
    """How to run it: model and render config, depth prior, z-range, resolution, category."""
    path: Path
    """The weights file."""
    sha256: str
    """SHA-256 of the weights file (provenance in eval summaries)."""
    step: int
    """Training steps behind these weights."""
    data_root: str | None = None
    """Dataset root the model was trained on (provenance; a default for ``depthnerf eval --data``)."""
    framing_origin: str = SPEC_FRAMING
    """Where ``spec.framing`` was read: :data:`SPEC_FRAMING`, or for older checkpoints the card it was derived
    from (:func:`~depthnerf.data.synth.framing.checkpoint_framing`)."""
    facing_head: FacingHead | None = None
    """The plane-angle head fitted on this model's features (:mod:`depthnerf.model.facing_head`), None when the
    file carries none."""


def load_pretrained(checkpoint: str | Path, device: torch.device | str = "cpu") -> Pretrained:
    """Load a checkpoint (shipped name or path) into a ready :class:`Pretrained` (weights in fp32 on ``device``:
    ``cpu``, ``cuda`` or ``cuda:N``, checked first, :func:`~depthnerf.distributed.pick_device`)."""
    pick_device(device, flag="device", auto=False)
    path = resolve_checkpoint(checkpoint)
    tensors, meta = read_weights(path)
    try:
        inference = spec_from_metadata(meta, str(path))
    except DepthnerfError as err:  # a check of the spec's own (its prior's name) that does not name the file
        if str(path) in str(err):
            raise
        raise DepthnerfError(f"{path}: inference spec: {err}") from None
    data_root = _data_root(meta)
    origin = SPEC_FRAMING
    if inference.framing is None:  # written before the spec held the framing: derived once, here
        framing, origin = checkpoint_framing(path, data_root, inference.category)
        inference = replace(inference, framing=framing)
    if inference.framing not in FRAMINGS:
        raise DepthnerfError(f"{path}: inference spec names framing {inference.framing!r} (expected one of "
                             f"{', '.join(FRAMINGS)})")
    step = meta.get("step", "0")
    if not step.isdigit():
        raise DepthnerfError(f"{path}: metadata 'step' is {step!r}, not a step count")
    inference = replace(inference, prior=portable_prior(inference.prior, inference.prior_weights_hash))
    model = PixelNeRF(inference.model, depth_aware=inference.depth_aware)
    head = head_from_tensors(tensors, meta, str(path))
    load_state_strict(model, {k: v.float() if v.is_floating_point() else v for k, v in tensors.items()
                              if not k.startswith(HEAD_PREFIX)}, path)
    if head is not None:
        check_encoder(head, model, str(path))
    model.to(device).eval()
    if head is not None:
        head.to(device).eval()
    return Pretrained(model=model, spec=inference, path=path, sha256=sha256_file(path),
                      step=int(step), data_root=data_root, framing_origin=origin, facing_head=head)


def _data_root(meta: dict[str, str]) -> str | None:
    """``data.root`` of the training config stored beside the weights (None when absent or unreadable)."""
    try:
        root = json.loads(meta["train_config"])["data"]["root"]
    except (KeyError, TypeError, ValueError):
        return None
    return root if isinstance(root, str) else None
