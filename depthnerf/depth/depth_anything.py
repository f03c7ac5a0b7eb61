"""The ``depth-anything-v2`` backend: Depth Anything V2 through ``transformers``, frozen.

Loading: ``checkpoint`` is a local directory (loaded with ``local_files_only=True``, never touching the network)
or a Hugging Face hub id (default ``depth-anything/Depth-Anything-V2-Base-hf``, the paper's model), first looked
up in the local Hugging Face cache, then on the hub; when neither works (offline) a
:class:`~depthnerf.errors.DepthnerfError` says how to pass a local directory instead. Only ``*.safetensors``
weights are read (``use_safetensors=True``: a ``pytorch_model.bin`` is never unpickled), the config must be a
relative Depth Anything model (``model_type`` ``depth_anything``, ``depth_estimation_type`` ``relative``: a metric
model outputs depth, not disparity), and the model's weights must be in the file with their shapes (weights that
would leave more than a tenth of the model at its random initialisation are refused as another network's, a few
missing tensors are a warning); each failure is one line naming the source.

Inference: the checkpoint's own image processor (``AutoImageProcessor``; for DA-V2: keep the aspect ratio, resize
so the sides are multiples of the 14-pixel patch, ImageNet mean/std) prepares a batch of ``[0, 1]`` images; the
model's ``predicted_depth`` (relative disparity: larger = closer) is resized back to the input's ``H x W`` with
the processor's ``post_process_depth_estimation`` (bicubic).

Weights hash: SHA-256 over ``*.safetensors`` plus ``config.json`` and ``preprocessor_config.json`` of a local
directory (file names and bytes: the weights sorted by name, then the two configs in that order; the configs are
included because they change the output), or of ``"hub:<id>@<revision>"`` for a hub id.

Licences: Depth-Anything-V2-Small is Apache-2.0; Depth-Anything-V2-Base and -Large are CC-BY-NC-4.0
(non-commercial).
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch
from jaxtyping import Float
from safetensors import SafetensorError
from torch import Tensor

from depthnerf.depth.backend import FrozenNetworkEstimator, PriorProvenance
from depthnerf.errors import DepthnerfError, UsageWarning
from depthnerf.files import sha256_files
from depthnerf.hub_access import hub_reachable

DEFAULT_CHECKPOINT = "depth-anything/Depth-Anything-V2-Base-hf"
"""The paper's estimator (Depth Anything V2 Base, relative depth)."""

DEFAULT_REVISION = "main"
"""Hub revision used when a hub id is given."""

HASHED_CONFIGS = ("config.json", "preprocessor_config.json")
"""Non-weight files of a local checkpoint directory that enter the weights hash."""


def licence_of(checkpoint: str) -> str:
    """Licence text of a Depth Anything V2 checkpoint, judged from its name (the hub id's repository or the
    directory's own name, never the folders above it)."""
    low = Path(checkpoint).name.lower()
    if "small" in low:
        return "Apache-2.0 (Depth-Anything-V2-Small)"
    if "base" in low or "large" in low:
        return "CC-BY-NC-4.0 (Depth-Anything-V2-Base/Large: non-commercial use only)"
    return "unknown: see the checkpoint's model card"


def _local_dir(checkpoint: str) -> Path | None:
    """The directory if ``checkpoint`` names one; an error if it looks like a path that does not exist."""
    path = Path(checkpoint).expanduser()
    if path.is_dir():
        return path
    if path.exists():
        raise DepthnerfError(f"{path}: a Depth Anything checkpoint must be a directory (save_pretrained layout)")
    if checkpoint.startswith((".", "/", "~")) or checkpoint.count("/") != 1:
        raise DepthnerfError(f"{checkpoint}: no such checkpoint directory (and not a hub id 'owner/name')")
    return None


def _hash_local_dir(path: Path) -> str:
    weights = sorted(path.glob("*.safetensors"))
    if not weights:
        pickled = " (pytorch_model.bin is never read: it would be unpickled; convert it to safetensors)" \
            if (path / "pytorch_model.bin").is_file() else ""
        raise DepthnerfError(f"{path}: no *.safetensors weights in the checkpoint directory{pickled}")
    configs = [path / name for name in HASHED_CONFIGS if (path / name).is_file()]
    return sha256_files(weights + configs)


def depth_anything_provenance(checkpoint: str | None = None) -> PriorProvenance:
    """Provenance (weights hash) of a DA-V2 checkpoint without loading the model."""
    checkpoint = checkpoint or DEFAULT_CHECKPOINT
    local = _local_dir(checkpoint)
    if local is not None:
        folder = local.resolve()
        digest = _hash_local_dir(folder)
        size = _processor_size(local)
        return PriorProvenance("depth-anything-v2", str(folder), digest, size, licence_of(str(folder)))
    digest = hashlib.sha256(f"hub:{checkpoint}@{DEFAULT_REVISION}".encode()).hexdigest()
    return PriorProvenance("depth-anything-v2", checkpoint, digest, 518, licence_of(checkpoint))


def _processor_size(path: Path) -> int | None:
    try:
        size = json.loads((path / "preprocessor_config.json").read_text()).get("size", {})
    except (OSError, ValueError):
        return None
    if isinstance(size, dict):
        return size.get("height") or size.get("shortest_edge")
    return size if isinstance(size, int) else None


def _check_local_config(path: Path) -> None:
    """A one-line error naming ``path/config.json`` when it is missing, not JSON or names no model type (what
    ``transformers`` would report as an unrecognised model)."""
    file = path / "config.json"
    if not file.is_file():
        raise DepthnerfError(f"{file}: missing; a Depth Anything checkpoint directory holds what save_pretrained "
                             "writes (config.json, model.safetensors, preprocessor_config.json)")
    try:
        data = json.loads(file.read_text())
    except (OSError, ValueError):  # UnicodeDecodeError is a ValueError
        raise DepthnerfError(f"{file}: not a valid JSON file") from None
    if not isinstance(data, dict) or "model_type" not in data:
        raise DepthnerfError(f"{file}: no 'model_type' entry (not a transformers model config)")


def _check_config(config, source: str) -> None:
    """Refuse a config that is not a relative Depth Anything model (module docstring)."""
    model_type = getattr(config, "model_type", None)
    if model_type != "depth_anything":
        raise DepthnerfError(f"{source}: config.json is a {model_type!r} model, not Depth Anything "
                             "('depth_anything'); pass a Depth Anything V2 checkpoint")
    kind = getattr(config, "depth_estimation_type", "relative")
    if kind != "relative":
        raise DepthnerfError(f"{source}: a {kind} Depth Anything model (it outputs depth, not the relative disparity "
                             f"the prior is); pass a relative one such as {DEFAULT_CHECKPOINT}")


REFUSED_SHARE = 0.1
"""Share of the model's tensors missing from (or mis-shaped in) the weights above which they are refused as another
network's; below it (a few keys a ``transformers`` version names differently) they load with a warning."""


def _check_loading_info(info: dict, source: str, total: int) -> None:
    """Refuse weights that would leave a real part of the model at its random initialisation (missing or mis-shaped
    tensors: more than :data:`REFUSED_SHARE` of the model's ``total``); warn about fewer."""
    missing, mismatched = list(info.get("missing_keys") or ()), list(info.get("mismatched_keys") or ())
    if not (missing or mismatched):
        return
    example = missing[0] if missing else mismatched[0]
    example = example[0] if isinstance(example, tuple) else example
    counts = f"{len(missing)} of its {total} tensors missing, {len(mismatched)} of another shape, e.g. {example}"
    if len(missing) + len(mismatched) > REFUSED_SHARE * max(total, 1):
        raise DepthnerfError(f"{source}: the weights do not fit the Depth Anything model of its config.json "
                             f"({counts}): weights of another network?")
    warnings.warn(f"{source}: {counts}; those stay at their initial values", UsageWarning, stacklevel=3)


@contextmanager
def _quiet_transformers() -> Iterator[None]:
    """``transformers`` logs only errors inside (its verbosity is restored after)."""
    from transformers.utils import logging as hf_logging

    previous = hf_logging.get_verbosity()
    hf_logging.set_verbosity_error()
    try:
        yield
    finally:
        hf_logging.set_verbosity(previous)


class DepthAnythingEstimator(FrozenNetworkEstimator):
    """Frozen Depth Anything V2 (any size) from ``transformers`` (``network``, with its image ``processor``);
    see the module docstring."""

    name = "depth-anything-v2"

    def __init__(self, network: torch.nn.Module, processor, provenance: PriorProvenance, device: str) -> None:
        super().__init__(network, provenance, device)
        self.processor = processor

    @classmethod
    def load(cls, checkpoint: str | None = None, device: str = "cpu") -> DepthAnythingEstimator:
        """Load from a local directory or a hub id (see the module docstring)."""
        from transformers import AutoConfig, AutoImageProcessor, AutoModelForDepthEstimation

        checkpoint = checkpoint or DEFAULT_CHECKPOINT
        provenance = depth_anything_provenance(checkpoint)
        local = _local_dir(checkpoint)
        if local is not None:
            _check_local_config(local)
        source = str(local) if local is not None else checkpoint
        attempts = [True] if local is not None else [True, False]  # local files / HF cache first, then the hub
        reason = ""
        for local_only in attempts:
            if not local_only and not hub_reachable():
                reason = "not in the local Hugging Face cache and the hub is unreachable"
                break
            try:
                kwargs = {"local_files_only": local_only}
                if local is None:
                    kwargs["revision"] = DEFAULT_REVISION
                config = AutoConfig.from_pretrained(source, **kwargs)
                _check_config(config, source)
                with _quiet_transformers():  # its multi-line load report: refused in one line below instead
                    model, info = AutoModelForDepthEstimation.from_pretrained(
                        source, config=config, use_safetensors=True, output_loading_info=True,
                        ignore_mismatched_sizes=True, **kwargs)  # mis-shaped: refused just below
                _check_loading_info(info, source, len(model.state_dict()))
                processor = AutoImageProcessor.from_pretrained(source, **kwargs)
                return cls(model, processor, provenance, device)
            except (OSError, ValueError, RuntimeError, SafetensorError) as err:  # missing or damaged files,
                # offline hub, undecodable JSON, weights of another size
                reason = (str(err).strip().splitlines() or [type(err).__name__])[0].split(". ")[0]
        if local is not None:
            raise DepthnerfError(f"{local}: not a loadable Depth Anything checkpoint ({reason})")
        raise DepthnerfError(
            f"cannot load Depth Anything checkpoint '{checkpoint}' ({reason}); download it where there is "
            f"internet (e.g. `hf download {checkpoint} --local-dir DIR`) and pass --depth-checkpoint DIR")

    @torch.inference_mode()
    def predict(self, images: Float[Tensor, "B 3 H W"],
                depths: Float[Tensor, "B H W"] | None = None) -> Float[Tensor, "B H W"]:
        """Relative disparity at the images' resolution (``depths`` is ignored)."""
        height, width = self.image_size(images)
        batch = images.detach().float().clamp(0.0, 1.0).cpu()
        inputs = self.processor(images=list(batch), return_tensors="pt", do_rescale=False)
        outputs = self.network(pixel_values=inputs["pixel_values"].to(self.device))
        outputs.predicted_depth = outputs.predicted_depth.float().cpu()
        post = self.processor.post_process_depth_estimation(outputs, target_sizes=[(height, width)] * len(batch))
        return torch.stack([item["predicted_depth"].reshape(height, width) for item in post])


def make_tiny_checkpoint(folder: Path, image_size: int = 42, seed: int = 0) -> Path:
    """Save a randomly initialised, tiny Depth Anything (Dinov2 backbone, 4 layers of width 16) and a DPT image
    processor configured like the real DA-V2 checkpoints (keep aspect ratio, multiples of 14, ImageNet
    normalisation) but at ``image_size`` to ``folder``. For tests and benchmarks of the real code path offline."""
    from transformers import (
        DepthAnythingConfig,
        DepthAnythingForDepthEstimation,
        Dinov2Config,
        DPTImageProcessor,
    )

    torch.manual_seed(seed)
    backbone = Dinov2Config(image_size=image_size, patch_size=14, hidden_size=16, num_hidden_layers=4,
                            num_attention_heads=2, intermediate_size=32,
                            out_features=["stage1", "stage2", "stage3", "stage4"], reshape_hidden_states=False)
    config = DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=16,
                                 neck_hidden_sizes=[8, 8, 16, 16], fusion_hidden_size=8, head_hidden_size=4)
    DepthAnythingForDepthEstimation(config).save_pretrained(folder)
    DPTImageProcessor(do_resize=True, size={"height": image_size, "width": image_size}, keep_aspect_ratio=True,
                      ensure_multiple_of=14, resample=3, do_rescale=True, do_normalize=True,
                      image_mean=[0.485, 0.456, 0.406], image_std=[0.229, 0.224, 0.225],
                      do_pad=False).save_pretrained(folder)
    return Path(folder)
