"""Image (+ depth prior) encoder: a torchvision ResNet trunk and, for the depth-aware model, a depth encoder.

Baseline (pixelNeRF, ``depth_aware=False``)
    Images in [0, 1] are scaled to [-1, 1] (pixelNeRF's ``Normalize(0.5, 0.5)``), then conv1 -> bn1 -> relu
    (stage 0, H/2), max-pool (if ``use_first_pool``), layer1 (stage 1), layer2 (stage 2), layer3 (stage 3).
    Every stage is upsampled to the stage-0 resolution with bilinear ``align_corners=True`` and the stages are
    concatenated: 64 + 64 + 128 + 256 = 512 channels at H/2 x W/2.

Depth-aware (the paper, ``depth_aware=True``); everything else identical
    * conv1 takes 4 channels: RGB in [-1, 1] and the normalised disparity prior (``depthnerf.depth.normalize``:
      foreground in [-4, 4], larger = nearer, background -5) times ``prior_scale`` (0.25: foreground in [-1, 1]).
      The 4th input channel's 7x7 kernels are initialised as the mean of the three RGB kernels (ImageNet weights
      and random init alike): at init the prior acts like a grey image.
    * a lightweight depth encoder on the (scaled) prior: conv3x3 stride 2 (1 -> depth_hidden) - BN - ReLU,
      conv3x3 (depth_hidden -> depth_hidden) - BN - ReLU, conv3x3 (depth_hidden -> depth_channels) - BN - ReLU,
      i.e. H/2 output (same grid as stage 0), receptive field 11x11 input pixels; 28,192 parameters for the
      defaults 32/64. Its maps are concatenated after the trunk's: C = 512 + 64 = 576.

Pretrained weights are optional and local only (``EncoderConfig.pretrained_path``): layer4/fc entries of a full
torchvision state_dict are ignored, any other missing or mis-shaped entry is an error.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
import torchvision
from jaxtyping import Float
from torch import Tensor, nn
from torchvision.models.resnet import BasicBlock

from depthnerf.errors import DepthnerfError
from depthnerf.model.config import EncoderConfig
from depthnerf.model.features import resize_bilinear
from depthnerf.model.norm import ObjectBatchNorm2d, ObjectGroups, object_groups
from depthnerf.state_dicts import read_state_dict

STAGE_NAMES = ("layer1", "layer2", "layer3")
"""Trunk stages after conv1, in order."""


class DepthEncoder(nn.Module):
    """Three conv-BN-ReLU layers mapping a 1-channel prior to ``depth_channels`` maps at half resolution."""

    def __init__(self, hidden: int, channels: int):
        super().__init__()
        layers: list[nn.Module] = []
        widths = [(1, hidden, 2), (hidden, hidden, 1), (hidden, channels, 1)]
        for c_in, c_out, stride in widths:
            layers += [nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
                       ObjectBatchNorm2d(c_out), nn.ReLU(inplace=True)]
        self.net = nn.Sequential(*layers)
        for m in self.net:
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, disparity: Float[Tensor, "N 1 H W"], groups: ObjectGroups | None = None
                ) -> Float[Tensor, "N Cd H2 W2"]:
        """``disparity``: the (scaled) normalised prior; ``groups``: the per-object BatchNorm plan of the encoder
        call (``depthnerf.model.norm``)."""
        x = disparity
        for layer in self.net:
            x = layer(x, groups) if isinstance(layer, ObjectBatchNorm2d) else layer(x)
        return x


def basic_block(block: BasicBlock, x: Tensor, groups: ObjectGroups | None) -> Tensor:
    """torchvision's ``BasicBlock.forward`` (the same operators in the same order, in place where it is), with
    ``groups`` given to its BatchNorm layers."""
    identity = x
    out = block.relu(block.bn1(block.conv1(x), groups))
    out = block.bn2(block.conv2(out), groups)
    if block.downsample is not None:
        conv, norm = block.downsample
        identity = norm(conv(x), groups)
    out += identity
    return block.relu(out)


class ResNetTrunk(nn.Module):
    """conv1/bn1/maxpool/layer1..layer3 of a torchvision ResNet; parameter names match torchvision's."""

    def __init__(self, cfg: EncoderConfig, depth_aware: bool):
        super().__init__()
        full = getattr(torchvision.models, cfg.backbone)(weights=None, norm_layer=ObjectBatchNorm2d)
        self.conv1 = full.conv1
        if depth_aware:
            self.conv1 = nn.Conv2d(4, 64, kernel_size=7, stride=2, padding=3, bias=False)
            with torch.no_grad():
                self.conv1.weight.copy_(expand_conv1(full.conv1.weight))
        self.bn1, self.relu, self.maxpool = full.bn1, full.relu, full.maxpool
        for name in STAGE_NAMES[: cfg.num_layers - 1]:
            setattr(self, name, getattr(full, name))
            if not all(isinstance(block, BasicBlock) for block in getattr(full, name)):
                raise DepthnerfError(f"encoder.backbone {cfg.backbone}: only BasicBlock ResNets are supported")
        self.num_layers = cfg.num_layers
        self.use_first_pool = cfg.use_first_pool
        self.depth_aware = depth_aware
        self.backbone = cfg.backbone
        del full  # layer4, avgpool and fc are dropped here: never part of the module or the optimiser

    def forward(self, x: Float[Tensor, "N Cin H W"], groups: ObjectGroups | None = None) -> list[Tensor]:
        """The feature stages; ``groups``: the per-object BatchNorm plan of the encoder call."""
        x = self.relu(self.bn1(self.conv1(x), groups))
        stages = [x]
        if self.num_layers > 1 and self.use_first_pool:
            x = self.maxpool(x)
        for name in STAGE_NAMES[: self.num_layers - 1]:
            for block in getattr(self, name):
                x = basic_block(block, x, groups)
            stages.append(x)
        return stages

    def load_torchvision_state(self, state: dict[str, Tensor], source: str) -> None:
        """Load a torchvision ResNet state_dict (ImageNet weights); conv1 is widened for the depth variant."""
        own = self.state_dict()
        used = {key.split(".")[0] for key in own}
        extra = [k for k in state if k.split(".")[0] in used and k not in own and "num_batches" not in k]
        if extra:
            raise DepthnerfError(f"{source}: unexpected entry '{extra[0]}' for a {self.backbone} trunk "
                                 "(wrong backbone?)")
        picked = {}
        for key, ref in own.items():
            if key not in state:
                raise DepthnerfError(f"{source}: pretrained weights lack '{key}' (not a torchvision ResNet?)")
            value = state[key].to(ref.dtype)
            if key == "conv1.weight" and self.depth_aware and tuple(value.shape) == (64, 3, 7, 7):
                value = expand_conv1(value)
            if value.shape != ref.shape:
                raise DepthnerfError(f"{source}: '{key}' has shape {tuple(value.shape)}, expected "
                                     f"{tuple(ref.shape)} (wrong backbone?)")
            picked[key] = value
        self.load_state_dict(picked)


def expand_conv1(weight: Float[Tensor, "64 3 7 7"]) -> Float[Tensor, "64 4 7 7"]:
    """A 4-input-channel conv1 kernel: RGB kernels unchanged, the 4th = their mean over the RGB channels."""
    return torch.cat([weight, weight.mean(dim=1, keepdim=True)], dim=1)


class ImageEncoder(nn.Module):
    """Encode source images (and priors) into pixel-aligned feature maps ``[N, C, Hf, Wf]`` (Hf = ceil(H'/2))."""

    def __init__(self, cfg: EncoderConfig, depth_aware: bool):
        super().__init__()
        self.cfg = cfg
        self.depth_aware = depth_aware
        self.trunk = ResNetTrunk(cfg, depth_aware)
        self.depth = DepthEncoder(cfg.depth_hidden, cfg.depth_channels) if depth_aware else None
        if cfg.pretrained_path is not None:
            self.trunk.load_torchvision_state(read_state_dict(cfg.pretrained_path, "pretrained encoder weights"),
                                             cfg.pretrained_path)

    @property
    def latent_size(self) -> int:
        """Feature channels C."""
        return self.cfg.latent_size(self.depth_aware)

    def forward(self, images: Float[Tensor, "N 3 H W"], disparity: Float[Tensor, "N 1 H W"] | None = None,
                objects: int = 1, *, image_stats: bool = False) -> Float[Tensor, "N C Hf Wf"]:
        """Feature maps of ``N = objects * V`` images; in training mode BatchNorm statistics are per object
        (``depthnerf.model.norm``: one plan per call, passed to every layer, folded at the end), so encoding B
        objects together equals encoding them one at a time; ``image_stats``: in evaluation mode too. With
        ``cfg.norm_stats == "batch"`` training mode pools them over all ``N`` images instead (one group)."""
        pooled = self.cfg.norm_stats == "batch" and self.training
        groups = object_groups(self, 1 if pooled else objects, image_stats)
        feats = self._forward(images, disparity, groups)
        groups.fold()
        return feats

    def _forward(self, images: Tensor, disparity: Tensor | None, groups: ObjectGroups) -> Tensor:
        x = images * 2.0 - 1.0
        if self.depth_aware:
            if disparity is None:
                raise DepthnerfError("depth-aware model (a depth prior is configured) needs a depth prior, got None")
            x = torch.cat([x, disparity * self.cfg.prior_scale], dim=1)
        if self.cfg.image_scale != 1.0:
            up = self.cfg.image_scale > 1.0
            x = F.interpolate(x, scale_factor=self.cfg.image_scale, mode="bilinear" if up else "area",
                              align_corners=True if up else None, recompute_scale_factor=True)
        stages = self.trunk(x, groups)
        size = stages[0].shape[-2:]
        maps = [stages[0]] + [resize_bilinear(s, size) for s in stages[1:]]
        if self.depth is not None:
            d = self.depth(x[:, 3:4], groups)
            if d.shape[-2:] != size:
                d = resize_bilinear(d, size)
            maps.append(d)
        return torch.cat(maps, dim=1)
