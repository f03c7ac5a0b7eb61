"""The ``bundled`` backend: the project's own small monocular depth network, shipped with the package.

Network (:class:`BundledDepthNet`): a compact U-Net behind a space-to-depth stem. The input is pixel-unshuffled
by ``unshuffle`` (default 4: 128 x 128 x 3 -> 32 x 32 x 48), so the U-Net runs at a quarter of the resolution;
level ``k`` works at ``1 / (unshuffle * 2**k)`` of the input with ``widths[k]`` channels (strided 3x3
convolution down, bilinear upsampling + skip concatenation up, BatchNorm + ReLU); the coarsest level also gets a
global-context vector (average-pooled features through a linear layer, broadcast back), which lets the network
reason about the whole object. The head predicts ``unshuffle**2`` sub-pixel values per location, pixel-shuffled
back to full resolution: one channel of relative disparity (larger = closer, up to scale and shift), like every
backend.

Inference (:class:`BundledEstimator`): images are resized (bilinear, antialiased) so the longer side is
``input_size`` and both sides are multiples of ``config.multiple``, run through the network, and the output is
resized back to the image (bilinear). Weights are a safetensors file whose metadata holds the JSON of
:class:`BundledNetConfig` (key ``config``) and free-form training notes. The weights hash is the SHA-256 of the
file.

Shipped nets (:data:`SHIPPED_NETS`, ``depthnerf/depth/weights``, ``MODEL_CARD.md`` there; all trained by
``scripts/train_bundled_depth.py`` on the synthetic benchmark's train split only). A ``--depth-checkpoint`` is
one of their names or a weights file; a name is what checkpoints and caches record, so they stay portable:

``srn`` (the default, :data:`DEFAULT_NET`)
    trained on SRN-framed 64 px renders, resized to 128 px as :func:`predict_at_image_size` does (8000 steps).
``srn-18k``
    the same data and command for 18000 steps; more accurate, and what ``cpu-cars-depth`` reads.
``legacy``
    the first net, trained on the legacy framing at 128 px; the depth-aware checkpoints trained before ``srn``
    existed read it (their recorded weights hash names it: :func:`shipped_net_named_by_hash`).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from jaxtyping import Float
from safetensors import SafetensorError
from safetensors.torch import load_file, safe_open
from torch import Tensor, nn

from depthnerf.depth.backend import FrozenNetworkEstimator, PriorProvenance
from depthnerf.errors import DepthnerfError
from depthnerf.files import sha256_files, write_bytes_atomic
from depthnerf.state_dicts import check_finite, load_state_strict, safetensors_bytes

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
"""Where the shipped nets live inside the package."""

SHIPPED_NETS: dict[str, Path] = {"srn": WEIGHTS_DIR / "bundled_depth_srn.safetensors",
                                 "srn-18k": WEIGHTS_DIR / "bundled_depth_srn18k.safetensors",
                                 "legacy": WEIGHTS_DIR / "bundled_depth.safetensors"}
"""The shipped nets by name (module docstring)."""

DEFAULT_NET = "srn"
"""The net a ``bundled`` prior without a ``--depth-checkpoint`` reads."""

DEFAULT_WEIGHTS = SHIPPED_NETS[DEFAULT_NET]
"""The default net's weights file."""

FORMAT = "depthnerf-bundled-depth-v1"
"""The ``format`` metadata entry :func:`save_bundled` writes (files without one are read too)."""

LICENCE = "MIT (depthnerf; trained only on the procedurally generated synthetic benchmark)"
"""Licence of the bundled weights."""


@dataclass(frozen=True)
class BundledNetConfig:
    """Architecture of the bundled depth U-Net."""

    widths: tuple[int, ...] = (24, 32, 48, 64, 128)
    """Channels per level; level ``k`` works at ``1 / (unshuffle * 2**k)`` of the network input's resolution
    (``1 / 2**k`` of the pixel-unshuffled input)."""
    input_size: int = 128
    """Images are resized so their longer side has this many pixels before the network."""
    context: bool = True
    """Add a global-context vector (pooled coarsest features) at the coarsest level."""
    unshuffle: int = 4
    """Space-to-depth factor: the U-Net runs at ``1 / unshuffle`` of the input resolution on pixel-unshuffled
    input and predicts ``unshuffle**2`` sub-pixels per location (pixel shuffle back to full resolution)."""

    @property
    def multiple(self) -> int:
        """Network input sides must be multiples of this (``unshuffle * 2**(levels - 1)``)."""
        return self.unshuffle * 2 ** (len(self.widths) - 1)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_json(cls, text: str) -> BundledNetConfig:
        """Parse :meth:`to_json`; ``KeyError`` / ``ValueError`` / ``TypeError`` for anything else, also for sizes
        no network can have (no levels, or a width, ``input_size`` or ``unshuffle`` below 1)."""
        raw = json.loads(text)
        config = cls(widths=tuple(int(w) for w in raw["widths"]), input_size=int(raw["input_size"]),
                     context=bool(raw["context"]), unshuffle=int(raw["unshuffle"]))
        if not config.widths or min(config.widths + (config.input_size, config.unshuffle)) < 1:
            raise ValueError(f"impossible bundled net sizes {config}")
        return config


def _conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class BundledDepthNet(nn.Module):
    """Compact U-Net: ``[B, 3, H, W]`` in [0, 1] -> relative disparity ``[B, H, W]`` (sides multiples of
    ``config.multiple``)."""

    def __init__(self, config: BundledNetConfig) -> None:
        super().__init__()
        self.config = config
        w = config.widths
        self.register_buffer("mean", torch.tensor([0.5, 0.5, 0.5]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor([0.25, 0.25, 0.25]).view(1, 3, 1, 1), persistent=False)
        r = config.unshuffle
        self.stem = nn.Sequential(nn.PixelUnshuffle(r), _conv_bn_relu(3 * r * r, w[0]), _conv_bn_relu(w[0], w[0]))
        self.down = nn.ModuleList(
            nn.Sequential(_conv_bn_relu(w[k - 1], w[k], stride=2), _conv_bn_relu(w[k], w[k]))
            for k in range(1, len(w)))
        self.context = nn.Linear(w[-1], w[-1]) if config.context else None
        self.up = nn.ModuleList(
            nn.Sequential(_conv_bn_relu(w[k] + w[k - 1], w[k - 1]), _conv_bn_relu(w[k - 1], w[k - 1]))
            for k in range(len(w) - 1, 0, -1))
        self.head = nn.Sequential(nn.Conv2d(w[0], r * r, 3, padding=1), nn.PixelShuffle(r))

    def forward(self, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B H W"]:
        m = self.config.multiple
        if images.shape[-1] % m or images.shape[-2] % m:
            raise ValueError(f"input sides {tuple(images.shape[-2:])} must be multiples of {m}")
        x = self.stem((images - self.mean) / self.std)
        skips = [x]
        for block in self.down:
            x = block(x)
            skips.append(x)
        if self.context is not None:
            x = x + self.context(x.mean(dim=(2, 3)))[:, :, None, None]
        for block, skip in zip(self.up, reversed(skips[:-1]), strict=True):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = block(torch.cat([x, skip], dim=1))
        return self.head(x)[:, 0]


def network_size(config: BundledNetConfig, height: int, width: int) -> tuple[int, int]:
    """Network input size for an ``height x width`` image: longer side ``input_size``, multiples of
    ``config.multiple``, aspect ratio kept as closely as that allows."""
    scale = config.input_size / max(height, width)
    m = config.multiple
    return max(m, round(height * scale / m) * m), max(m, round(width * scale / m) * m)


def predict_at_image_size(network: BundledDepthNet, images: Float[Tensor, "B 3 H W"]) -> Float[Tensor, "B H W"]:
    """Disparity at the images' own size: resized (bilinear, antialiased) to :func:`network_size`, run, and resized
    back (bilinear). Inference (:meth:`BundledEstimator.predict`) and training (``scripts/train_bundled_depth.py``)
    both go through here, so the network is trained on what it sees at inference."""
    height, width = images.shape[-2:]
    size = network_size(network.config, height, width)
    if size == (height, width):
        return network(images)
    x = F.interpolate(images, size=size, mode="bilinear", align_corners=False, antialias=True)
    return F.interpolate(network(x)[:, None], size=(height, width), mode="bilinear", align_corners=False)[:, 0]


def save_bundled(net: BundledDepthNet, path: Path, notes: dict[str, str] | None = None) -> None:
    """Write weights + config atomically (:func:`depthnerf.files.write_bytes_atomic`)."""
    state = {k: v.detach().float().cpu().contiguous() for k, v in net.state_dict().items()
             if v.dtype.is_floating_point}
    state.update({k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()
                  if not v.dtype.is_floating_point})
    metadata = {"config": net.config.to_json(), "format": FORMAT, **(notes or {})}
    write_bytes_atomic(path, safetensors_bytes(state, metadata=metadata))  # shared data: 0644


def shipped_net_name(checkpoint: str | os.PathLike | None) -> str | None:
    """The shipped net ``checkpoint`` names (None: the default), else None (a weights file)."""
    if checkpoint is None:
        return DEFAULT_NET
    return str(checkpoint) if str(checkpoint) in SHIPPED_NETS else None


def shipped_nets_text() -> str:
    """The shipped nets' names for help texts, the default marked, e.g. ``srn (the default), srn-18k, legacy``."""
    return ", ".join(f"{name} (the default)" if name == DEFAULT_NET else name for name in SHIPPED_NETS)


def shipped_net_named_by_hash(weights_hash: str) -> str | None:
    """The name of the shipped net whose file has SHA-256 ``weights_hash`` (None: no shipped net has it)."""
    for name, path in SHIPPED_NETS.items():
        if path.is_file() and sha256_files([path], names=False) == weights_hash:
            return name
    return None


def _weights_path(checkpoint: str | os.PathLike | None) -> Path:
    name = shipped_net_name(checkpoint)
    path = SHIPPED_NETS[name] if name is not None else Path(checkpoint).expanduser()
    if name is not None and not path.is_file():
        raise DepthnerfError(f"{path}: bundled depth weights not found (reproduce with: python "
                             "scripts/train_bundled_depth.py)")
    if path.is_dir():
        raise DepthnerfError(f"{path}: a directory; bundled depth weights are one .safetensors file or a shipped "
                             f"net's name ({shipped_nets_text()})")
    if not path.is_file():
        raise DepthnerfError(f"{checkpoint}: not found: neither a shipped bundled net ({shipped_nets_text()}) nor a "
                             "weights file")
    return path


def _read_config(path: Path) -> tuple[BundledNetConfig, dict[str, str]]:
    """The config and metadata of a bundled weights file; one line naming the file when it is not one."""
    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = dict(handle.metadata() or {})
    except (SafetensorError, OSError) as err:
        raise DepthnerfError(f"{path}: unreadable bundled depth weights (not a safetensors file: {err})") from None
    kind = metadata.get("format", FORMAT)
    if kind != FORMAT:
        hint = ("; a depthnerf model checkpoint goes to --checkpoint, not --depth-checkpoint"
                if kind.startswith("depthnerf-checkpoint") else "")
        raise DepthnerfError(f"{path}: a {kind!r} safetensors file, not bundled depth weights ({FORMAT}){hint}")
    if "config" not in metadata:
        raise DepthnerfError(f"{path}: a safetensors file without a bundled depth net's 'config' metadata (not "
                             "written by save_bundled: another network's weights?)")
    try:
        return BundledNetConfig.from_json(metadata["config"]), metadata
    except (KeyError, ValueError, TypeError, AttributeError):
        raise DepthnerfError(f"{path}: bundled depth weights lack a valid 'config' metadata entry") from None


def load_bundled_net(checkpoint: str | os.PathLike | None = None) -> tuple[BundledDepthNet, dict[str, str]]:
    """The network (eval mode, frozen) and the file's metadata; errors name the file."""
    path = _weights_path(checkpoint)
    config, metadata = _read_config(path)
    try:
        state = load_file(str(path))
    except (SafetensorError, OSError) as err:
        raise DepthnerfError(f"{path}: unreadable bundled depth weights ({err})") from None
    net = BundledDepthNet(config)
    check_finite(state, path, "damaged weights")
    load_state_strict(net, state, path, "weights do not match the config in the file")
    return net.eval().requires_grad_(False), metadata


def bundled_provenance(checkpoint: str | os.PathLike | None = None) -> PriorProvenance:
    """Provenance of the bundled weights (SHA-256 of the file) without building the network."""
    path = _weights_path(checkpoint)
    size = _read_config(path)[0].input_size
    shown = shipped_net_name(checkpoint) or str(path.resolve())
    return PriorProvenance("bundled", shown, sha256_files([path], names=False), size, LICENCE)


class BundledEstimator(FrozenNetworkEstimator):
    """The frozen bundled network (``network``) behind the :class:`~depthnerf.depth.estimators.DepthEstimator`
    interface."""

    name = "bundled"

    @classmethod
    def load(cls, checkpoint: str | os.PathLike | None = None, device: str = "cpu") -> BundledEstimator:
        """Load a shipped net by name (None: the default) or a file written by :func:`save_bundled`."""
        net, _ = load_bundled_net(checkpoint)
        return cls(net, bundled_provenance(checkpoint), device)

    @torch.inference_mode()
    def predict(self, images: Float[Tensor, "B 3 H W"],
                depths: Float[Tensor, "B H W"] | None = None) -> Float[Tensor, "B H W"]:
        """Relative disparity at the images' resolution (``depths`` is ignored)."""
        self.image_size(images)  # checks the shape
        x = images.detach().float().clamp(0.0, 1.0).to(self.device)
        return predict_at_image_size(self.network, x).float().cpu()
