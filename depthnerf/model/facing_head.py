"""A facing head: the angle of the object's mirror plane read from the encoder's features by a linear map.

A mirror model needs the object's mirror plane, and a photo does not say which way its object faces. The input
view rendered under each candidate plane (:mod:`depthnerf.infer.facing`) finds the plane's angle to a few degrees,
but it cannot tell a side view from a front view: at both, the plane at right angles to the viewing direction maps
each visible point onto its own ray and renders the input view as well as the right plane. What the object looks
like can: a car seen from the side is long and low, seen from the front narrow and tall.

The head is ridge regression from the input view's feature maps, average-pooled to a ``grid x grid`` layout and
standardised, to the doubled angle ``(cos 2 psi, sin 2 psi)`` of the plane relative to the camera
(:func:`~depthnerf.data.symmetry.relative_facing`; doubled because ``psi`` and ``psi + 180`` are one plane):

    w = argmin ||Z w - Y||^2 + lambda ||w||^2 = Z^T (Z Z^T + lambda I)^-1 Y      (Z: N x D standardised features)

and ``psi = atan2(y_sin, y_cos) / 2``. It is fitted after training on the frozen network's features of the
training views, whose planes are known (:func:`fit_ridge`; ``depthnerf fit-facing``), and travels in the weights
file under :data:`PREFIX` with :data:`META_KEY` metadata.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from depthnerf.errors import DepthnerfError

PREFIX = "facing_head."
"""Key prefix of the head's tensors in a weights file."""
META_KEY = "facing_head"
"""Metadata key of the head's JSON description (:meth:`FacingHead.describe`) in a weights file."""


def pool_features(features: Float[Tensor, "B C Hf Wf"], grid: int) -> Float[Tensor, "B D"]:
    """The regression's input: feature maps average-pooled to ``grid x grid`` and flattened (D = C grid^2)."""
    return F.adaptive_avg_pool2d(features.float(), grid).flatten(1)


class FacingHead(nn.Module):
    """``psi`` (degrees, [0, 180)) from one view's feature maps (module docstring). Buffers only: it is fitted in
    closed form, never by gradients."""

    def __init__(self, channels: int, grid: int, info: dict | None = None) -> None:
        super().__init__()
        if grid < 1 or channels < 1:
            raise DepthnerfError(f"facing head: grid and channels must be positive, got {grid} and {channels}")
        self.grid = int(grid)
        self.info = dict(info or {})
        dim = channels * grid * grid
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("inv_std", torch.ones(dim))
        self.register_buffer("weight", torch.zeros(dim, 2))
        self.register_buffer("bias", torch.zeros(2))

    @property
    def channels(self) -> int:
        return self.mean.shape[0] // (self.grid * self.grid)

    def doubled(self, pooled: Float[Tensor, "B D"]) -> Float[Tensor, "B 2"]:
        """The regression's output, the estimate of ``(cos 2 psi, sin 2 psi)``, from already pooled features
        (:func:`pool_features` with this head's grid)."""
        return ((pooled - self.mean) * self.inv_std) @ self.weight + self.bias

    def predict(self, pooled: Float[Tensor, "B D"]) -> Float[Tensor, " B"]:
        """``psi`` from already pooled features: ``atan2(y_sin, y_cos) / 2`` of :meth:`doubled`."""
        return self.estimate(pooled)[0]

    def confidence(self, pooled: Float[Tensor, "B D"]) -> Float[Tensor, " B"]:
        """The length of :meth:`doubled`: about 1 for a view whose features the head maps onto one angle, near 0
        where they fall between angles (the ridge fit averages unit vectors that point apart). A low value marks
        the head's large errors: on unseen synthetic chairs, views below 0.4 were 14-19 degrees off at the
        median, the rest 4-5 (docs/RESULTS.md, "When the facing head is unsure")."""
        return self.estimate(pooled)[1]

    def estimate(self, pooled: Float[Tensor, "B D"]) -> tuple[Float[Tensor, " B"], Float[Tensor, " B"]]:
        """``(psi, confidence)`` (:meth:`predict`, :meth:`confidence`) from one regression of ``pooled``."""
        y = self.doubled(pooled)
        return torch.rad2deg(torch.atan2(y[:, 1], y[:, 0]) / 2) % 180.0, y.norm(dim=1)

    def forward(self, features: Float[Tensor, "B C Hf Wf"]) -> Float[Tensor, " B"]:
        return self.read(features)[0]

    def read(self, features: Float[Tensor, "B C Hf Wf"]) -> tuple[Float[Tensor, " B"], Float[Tensor, " B"]]:
        """``(psi, confidence)`` from one view's feature maps (:meth:`estimate`)."""
        if features.ndim != 4 or features.shape[1] != self.channels:
            raise DepthnerfError(f"facing head: expects [B, {self.channels}, H, W] features, got "
                                 f"{list(features.shape)} (a head fitted on another model?)")
        pooled = pool_features(features, self.grid)
        return self.estimate(pooled)

    def describe(self) -> dict:
        """JSON-ready: the grid, channels and what :func:`fit_ridge`'s caller recorded (``info``)."""
        return {"grid": self.grid, "channels": self.channels, **self.info}


def doubled_angle(psi_deg: Float[Tensor, " N"]) -> Float[Tensor, "N 2"]:
    """``(cos 2 psi, sin 2 psi)``: the regression target, the same for ``psi`` and ``psi + 180``."""
    t = torch.deg2rad(psi_deg.double()) * 2
    return torch.stack([torch.cos(t), torch.sin(t)], dim=-1)


def angle_error(estimate_deg: Tensor | float, true_deg: Tensor | float) -> Tensor | float:
    """``estimate - true`` for plane angles (modulo 180), in [-90, 90) degrees (tensors or plain floats)."""
    return (estimate_deg - true_deg + 90.0) % 180.0 - 90.0


def fit_ridge(pooled: Float[Tensor, "N D"], psi_deg: Float[Tensor, " N"], lam: float, channels: int, grid: int,
              info: dict | None = None) -> FacingHead:
    """The :class:`FacingHead` minimising the ridge objective (module docstring) on standardised ``pooled``
    features (:func:`fit_ridges` with one weight)."""
    return fit_ridges(pooled, psi_deg, [lam], channels, grid, info)[0]


def fit_ridges(pooled: Float[Tensor, "N D"], psi_deg: Float[Tensor, " N"], lams: Sequence[float], channels: int,
               grid: int, info: dict | None = None) -> list[FacingHead]:
    """:func:`fit_ridge` for each weight of ``lams``, solved in float64 in whichever of the primal (``D x D``) and
    dual (``N x N``) forms is smaller, its Gram matrix formed once for all of them; the targets are centred, so
    the bias is their mean."""
    if pooled.ndim != 2 or pooled.shape[0] != psi_deg.shape[0] or pooled.shape[1] != channels * grid * grid:
        raise DepthnerfError(f"fit_ridge: {list(pooled.shape)} features for {psi_deg.shape[0]} angles "
                             f"(expected N x {channels * grid * grid})")
    for lam in lams:
        if not lam > 0 or not math.isfinite(lam):
            raise DepthnerfError(f"fit_ridge: lambda must be a positive number, got {lam}")
    x = pooled.double()
    mean = x.mean(0)
    inv_std = 1.0 / (x.std(0, correction=0) + 1e-6)
    z = (x - mean) * inv_std
    y = doubled_angle(psi_deg)
    bias = y.mean(0)
    y = y - bias
    n, d = z.shape
    primal = d <= n
    gram = z.T @ z if primal else z @ z.T
    heads = []
    for lam in lams:
        system = gram + lam * torch.eye(gram.shape[0], dtype=z.dtype)
        weight = torch.linalg.solve(system, z.T @ y) if primal else z.T @ torch.linalg.solve(system, y)
        head = FacingHead(channels, grid, info)
        head.mean.copy_(mean.float())
        head.inv_std.copy_(inv_std.float())
        head.weight.copy_(weight.float())
        head.bias.copy_(bias.float())
        heads.append(head)
    return heads


def encoder_fingerprint(model: nn.Module) -> str:
    """SHA-256 (first 16 hex digits) of the ``encoder.*`` state of ``model`` rounded to float16: the features a
    head was fitted on, the same for a run's float32 weights and their float16 export."""
    digest = hashlib.sha256()
    for key, value in sorted(model.state_dict().items()):
        if key.startswith("encoder."):
            v = value.detach().cpu()
            v = v.half() if v.is_floating_point() else v
            digest.update(key.encode())
            digest.update(v.contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


def check_encoder(head: FacingHead, model: nn.Module, where: str) -> None:
    """Refuse ``head`` unless it was fitted on ``model``'s encoder (:func:`encoder_fingerprint`); ``where`` starts
    the one-line error."""
    fingerprint = encoder_fingerprint(model)
    if head.info.get("encoder") != fingerprint:
        raise DepthnerfError(f"{where}: its facing head was fitted on another encoder (fingerprint "
                             f"{head.info.get('encoder')}, this model's is {fingerprint})")


def head_tensors(head: FacingHead) -> tuple[dict[str, Tensor], dict[str, str]]:
    """The head as weights-file entries: tensors under :data:`PREFIX` and its :data:`META_KEY` metadata."""
    tensors = {PREFIX + k: v.detach().cpu().contiguous() for k, v in head.state_dict().items()}
    return tensors, {META_KEY: json.dumps(head.describe(), sort_keys=True)}


def head_from_tensors(tensors: dict[str, Tensor], meta: dict[str, str], where: str) -> FacingHead | None:
    """The head stored in a weights file (None when it has none); ``tensors`` are the file's tensors with the
    :data:`PREFIX` ones (errors name ``where``)."""
    own = {k[len(PREFIX):]: v for k, v in tensors.items() if k.startswith(PREFIX)}
    if not own and META_KEY not in meta:
        return None
    try:
        info = json.loads(meta[META_KEY])
        grid, channels = int(info["grid"]), int(info["channels"])
    except (KeyError, TypeError, ValueError):
        raise DepthnerfError(f"{where}: facing head tensors without a valid '{META_KEY}' metadata entry") from None
    head = FacingHead(channels, grid, {k: v for k, v in info.items() if k not in ("grid", "channels")})
    expected = {k: tuple(v.shape) for k, v in head.state_dict().items()}
    found = {k: tuple(v.shape) for k, v in own.items()}
    if found != expected:
        raise DepthnerfError(f"{where}: facing head tensors {found} do not match its metadata (expected {expected})")
    head.load_state_dict({k: v.float() for k, v in own.items()})
    return head
