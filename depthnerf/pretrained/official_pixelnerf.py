"""The official pixelNeRF weights (sxyu/pixel-nerf, e.g. its released ``srn_car`` / ``srn_chair`` models) as a
depthnerf baseline model, so that pixelNeRF's own weights are scored by this package's evaluation.

The two networks compute the same function (:mod:`depthnerf.model`'s docstrings give the correspondence: the
torchvision trunk to layer3, bilinear ``align_corners`` upsampling, the ``ResnetFC`` MLP with ``lin_z`` before the
combine layer, the positional encoding ``x, sin(f_0 x), cos(f_0 x), sin(f_1 x), ...`` with ``f_k = freq_factor *
2^k``). The state dict maps name for name (``encoder.model.*`` -> ``encoder.trunk.*``, ``mlp_coarse.*`` ->
``coarse.*``, ``mlp_fine.*`` -> ``fine.*``) but for ONE difference of convention: pixelNeRF reads SRN poses in
OpenGL camera axes (x right, y up, z backward: SRN's OpenCV poses times ``diag(1, -1, -1, 1)``), this package in
OpenCV axes (``depthnerf.data.cameras``). A point rotated into the source camera, and the view direction, have
the signs of their y and z flipped between the two, so the MLP input columns that carry them change sign:

* the raw coordinates (y, z) and the view direction (y, z): ``-1``;
* ``sin(f_k y)``, ``sin(f_k z)``: ``-1`` (sine is odd); ``cos(f_k y)``, ``cos(f_k z)``: unchanged (cosine is even).

``lin_in``'s weight columns are multiplied by those signs; every other tensor is copied. The projection is the
same in both conventions (pixelNeRF negates both the division and its y focal length), and so are the features.

Tensors that are no part of the network are ignored: ``layer4`` and ``fc`` of the torchvision trunk (built by
pixelNeRF, never used), the positional encoding's buffers (``code._freqs``, checked against the model config, and
``code._phases``) and the encoder's cached state of older versions (``encoder.latent``, ``encoder.latent_scaling``).
Anything else that does not fit (another config's layers, a global encoder) is one error line naming the file.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from depthnerf.errors import DepthnerfError
from depthnerf.model.config import FieldConfig, PixelNeRFConfig
from depthnerf.state_dicts import read_state_dict

RENAMES = (("encoder.model.", "encoder.trunk."), ("mlp_coarse.", "coarse."), ("mlp_fine.", "fine."))
"""Official name prefix -> this package's, for every tensor that is part of both networks."""
IGNORED_PREFIXES = ("encoder.model.layer4.", "encoder.model.fc.", "code.", "encoder.latent")
"""Official tensors that are no part of the network this package evaluates (module docstring)."""


def input_signs(cfg: FieldConfig) -> torch.Tensor:
    """``[d_in]`` signs taking the MLP input columns of pixelNeRF's OpenGL camera axes to OpenCV's: -1 on the
    columns of y and z in the raw coordinates, the sines and the view direction, +1 elsewhere (module docstring)."""
    flip = torch.tensor([1.0, -1.0, -1.0])
    parts = [flip] if cfg.include_input else []
    for _ in range(cfg.num_freqs):
        parts += [flip, torch.ones(3)]  # sin(f_k x) (odd), then cos(f_k x) (even)
    if cfg.use_viewdirs:
        parts.append(flip)
    return torch.cat(parts)


def read_official_state(path: Path) -> dict[str, torch.Tensor]:
    """The state dict in an official pixelNeRF weights file (``torch.save`` of ``PixelNeRFNet.state_dict()``, e.g.
    ``pixel_nerf_latest``), read with ``weights_only=True`` (never unpickled); a ``.safetensors`` file is read
    as such. Errors name the file."""
    return read_state_dict(path, "official pixelNeRF weights")


def _check_encoding(state: dict[str, torch.Tensor], cfg: FieldConfig, path: Path) -> None:
    """The file's positional-encoding frequencies (``code._freqs``: each ``f_k`` twice) against the config's."""
    freqs = state.get("code._freqs")
    if freqs is None:
        return
    expected = [cfg.freq_factor * 2.0**k for k in range(cfg.num_freqs) for _ in range(2)]
    found = freqs.flatten().double().tolist()
    same = len(found) == len(expected) and all(
        math.isclose(a, b, rel_tol=1e-6) for a, b in zip(found, expected, strict=True))
    if not same:
        raise DepthnerfError(f"{path}: code._freqs is {[round(f, 4) for f in found[::2]]}, the model config "
                             f"encodes with {[round(f, 4) for f in expected[::2]]} (num_freqs {cfg.num_freqs}, "
                             f"freq_factor {cfg.freq_factor}); not a model of this config")


def convert_official_state(state: dict[str, torch.Tensor], cfg: PixelNeRFConfig, path: Path
                           ) -> dict[str, torch.Tensor]:
    """This package's state dict (baseline :class:`~depthnerf.model.pixelnerf.PixelNeRF` of ``cfg``) holding the
    official weights ``state`` (module docstring). Keys and shapes are checked when the result is loaded
    (:func:`depthnerf.state_dicts.load_state_strict`); here an official tensor that maps to nothing is an error."""
    if cfg.mirror or cfg.point_columns:
        raise DepthnerfError(f"{path}: official pixelNeRF weights load into the plain pixelNeRF model, not one "
                             "with mirror conditioning or source pixels at the point")
    if cfg.fine is not None and cfg.fine.d_in != cfg.coarse.d_in:
        raise DepthnerfError(f"{path}: the model config's coarse and fine inputs differ; pixelNeRF's share one")
    _check_encoding(state, cfg.coarse, path)
    out: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        if key.startswith(IGNORED_PREFIXES):
            continue
        new = next((target + key[len(source):] for source, target in RENAMES if key.startswith(source)), None)
        if new is None:
            raise DepthnerfError(f"{path}: tensor {key!r} is no part of pixelNeRF's SRN network (another config, "
                                 "e.g. a global encoder, or not a pixelNeRF file)")
        out[new] = value.detach().clone()
    for net, field_cfg in (("coarse", cfg.coarse), ("fine", cfg.fine)):
        key = f"{net}.lin_in.weight"
        if field_cfg is None or key not in out:
            continue  # a missing tensor is reported by the strict load
        signs = input_signs(field_cfg)
        if out[key].shape[-1] != signs.numel():
            raise DepthnerfError(f"{path}: {key.replace(net, 'mlp_' + net, 1)} takes {out[key].shape[-1]} inputs, "
                                 f"the model config's encoding has {signs.numel()}; not a model of this config")
        out[key] = out[key] * signs.to(out[key].dtype)
    return out
