"""The monocular depth estimator interface every backend implements, its provenance record, and the oracle.

Convention (all backends): RGB images ``[B, 3, H, W]`` in [0, 1] in, *relative disparity* ``[B, H, W]`` out at
the input's resolution: larger = closer, defined up to an unknown positive scale and a shift (see
``depthnerf/data/cameras.py`` for z-depth vs disparity). The backends are named in ONE registry,
:data:`depthnerf.depth.estimators.ESTIMATORS`.
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass
from typing import Any, Protocol, runtime_checkable

import torch
from jaxtyping import Float
from torch import Tensor

from depthnerf.errors import DepthnerfError


@dataclass(frozen=True)
class PriorProvenance:
    """Where a depth prior came from: enough to key a cache and to record in a run folder."""

    estimator: str
    """Backend name (one of ``ESTIMATORS``)."""
    checkpoint: str | None
    """Hub id, local directory or weights file the backend was loaded from (None: the backend's default)."""
    weights_hash: str
    """Hex SHA-256 identifying the weights (file contents, or hub id + revision when not local)."""
    input_resolution: int | None
    """Side length the backend resizes images to internally (None: works at the image's own resolution)."""
    licence: str
    """Licence of the weights (for READMEs and run folders)."""

    @property
    def short_hash(self) -> str:
        """The first 12 hex digits of :attr:`weights_hash` (used in cache folder names)."""
        return self.weights_hash[:12]

    def as_dict(self) -> dict[str, Any]:
        """A JSON-able dict."""
        return asdict(self)


@runtime_checkable
class DepthEstimator(Protocol):
    """A frozen monocular depth estimator (see the module docstring for the disparity convention)."""

    name: str
    """Backend name."""
    needs_depth: bool
    """True only for ``oracle``: ``predict`` then requires ground-truth ``depths``."""

    @property
    def provenance(self) -> PriorProvenance:
        """Backend, weights hash and resolution."""
        ...

    def predict(self, images: Float[Tensor, "B 3 H W"],
                depths: Float[Tensor, "B H W"] | None = None) -> Float[Tensor, "B H W"]:
        """Relative disparity at the images' resolution (float32, on the CPU)."""
        ...


class FrozenNetworkEstimator:
    """What the network backends share: a frozen module on a device, its provenance and the input check."""

    name: str
    needs_depth = False

    def __init__(self, network: torch.nn.Module, provenance: PriorProvenance, device: str = "cpu") -> None:
        self.network = network.eval().requires_grad_(False).to(device)
        self._provenance = provenance
        self.device = device

    @property
    def provenance(self) -> PriorProvenance:
        return self._provenance

    @staticmethod
    def image_size(images: Float[Tensor, "B 3 H W"]) -> tuple[int, int]:
        """(H, W) of a ``[B, 3, H, W]`` batch; ``ValueError`` for any other shape."""
        if images.ndim != 4 or images.shape[1] != 3:
            raise ValueError(f"expected images [B, 3, H, W], got {tuple(images.shape)}")
        return int(images.shape[-2]), int(images.shape[-1])


def oracle_disparity(depth: Float[Tensor, "*B H W"]) -> Float[Tensor, "*B H W"]:
    """Ground-truth disparity: ``1 / z`` where ``z > 0`` (foreground), 0 on the background."""
    depth = depth.float()
    return torch.where(depth > 0, 1.0 / depth.clamp_min(1e-12), torch.zeros_like(depth))


class OracleEstimator:
    """The ``oracle`` backend: disparity from ground-truth z-depth (images are ignored)."""

    name = "oracle"
    needs_depth = True

    @property
    def provenance(self) -> PriorProvenance:
        return oracle_provenance()

    def predict(self, images: Float[Tensor, "B 3 H W"],
                depths: Float[Tensor, "B H W"] | None = None) -> Float[Tensor, "B H W"]:
        if depths is None:
            raise DepthnerfError("the 'oracle' depth prior needs ground-truth depth maps (dataset depth/ folder)")
        if depths.shape[0] != images.shape[0] or depths.shape[-2:] != images.shape[-2:]:
            raise ValueError(f"depths {tuple(depths.shape)} do not match images {tuple(images.shape)}")
        return oracle_disparity(depths)


def oracle_provenance() -> PriorProvenance:
    """Provenance of the oracle (its 'weights hash' is the hash of its definition string)."""
    digest = hashlib.sha256(b"oracle: 1/z on foreground, 0 on background").hexdigest()
    return PriorProvenance("oracle", None, digest, None, "n/a (ground truth)")
