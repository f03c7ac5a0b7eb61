"""Configuration of the (depth-aware) pixelNeRF network: one dataclass per component.

Defaults reproduce pixelNeRF's SRN configuration (``conf/default_mv.conf`` of sxyu/pixel-nerf): ResNet34 trunk
with the first max-pool, conv1 + layer1..layer3 (512 feature channels), a 5-block residual MLP of width 512 with
features injected before blocks 0-2 and views averaged at block 3, 6 positional-encoding frequencies
``1.5 * 2^k``, raw view directions, separate coarse and fine networks. The paper's method and the baseline
differ by ONE switch, the depth prior: whether a model is depth-aware (the ``depth_aware`` argument below and of
the model's constructor) is :attr:`depthnerf.depth.prior.PriorConfig.enabled`, never stored in a config.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from depthnerf.errors import DepthnerfError

EncoderNorm = Literal["running", "image"]
"""How the encoder's BatchNorm layers normalise at inference (:meth:`depthnerf.model.pixelnerf.PixelNeRF.encode`):
their running statistics (pixelNeRF) or each object's own source-view statistics, as training does."""
ENCODER_NORMS: tuple[str, ...] = ("running", "image")
"""The :data:`EncoderNorm` values (``depthnerf eval --encoder-norm`` takes its choices from here: this module
imports no torch)."""
NormStats = Literal["object", "batch"]
"""Whose statistics the encoder's BatchNorm layers normalise with in training (:attr:`EncoderConfig.norm_stats`)."""
NORM_STATS: tuple[str, ...] = ("object", "batch")
"""The :data:`NormStats` values."""

PRIOR_POINT_SCALE = 0.2
"""Factor on the normalised prior (foreground in [-4, 4], background -5) where it enters the MLP input
(:attr:`PixelNeRFConfig.prior_at_point`): background -1, foreground within [-0.8, 0.8]."""

TRUNK_CHANNELS: dict[str, tuple[int, ...]] = {"resnet18": (64, 64, 128, 256), "resnet34": (64, 64, 128, 256)}
"""Channels of the feature stages conv1, layer1, layer2, layer3 of each supported torchvision trunk."""


@dataclass
class EncoderConfig:
    """The image (+ depth prior) encoder producing pixel-aligned feature maps at half the input resolution."""

    backbone: Literal["resnet34", "resnet18"] = "resnet34"
    """torchvision ResNet whose conv1/bn1/layer1..layer3 form the trunk (layer4 and the head are never built
    into the module, so they are neither stored nor optimised)."""
    num_layers: int = 4
    """Number of feature stages concatenated (pixelNeRF ``num_layers``): 1 = conv1 only (64 channels),
    2 = + layer1 (128), 3 = + layer2 (256), 4 = + layer3 (512)."""
    use_first_pool: bool = True
    """Apply the ResNet max-pool before layer1 (pixelNeRF default True)."""
    image_scale: float = 1.0
    """Resize factor applied to the images (and prior) before the trunk (pixelNeRF ``feature_scale``); e.g.
    0.5 encodes 128x128 inputs at 64x64. Projection still uses the original image size."""
    pretrained_path: str | None = None
    """Optional local torchvision ``resnetXX`` ImageNet state_dict (``.safetensors``, or ``.pth``/``.pt`` read with
    ``torch.load(weights_only=True)``). None = random initialisation (nothing is ever downloaded)."""
    prior_scale: float = 0.25
    """Factor applied to the prior before conv1 and the depth encoder. Priors are
    ``depthnerf.depth.normalize.normalize_disparity`` outputs (foreground in [-4, 4], background -5), so 0.25 puts
    the foreground in [-1, 1] like the images."""
    depth_hidden: int = 32
    """Width of the first two conv layers of the depth encoder (depth-aware models only)."""
    depth_channels: int = 64
    """Output channels of the depth encoder, concatenated to the trunk features (depth-aware models only)."""
    norm_stats: NormStats = "object"
    """Whose statistics the encoder's BatchNorm layers normalise with in training (evaluation uses their running
    statistics either way). ``object``: each object's own source views (``depthnerf.model.norm``), so a step's
    result does not depend on which objects share its batch or rank; with one source view, the image's own
    per-channel mean and variance. ``batch``: pooled over the step's whole batch (on each DDP rank, its own part),
    as pixelNeRF's BatchNorm does; an object's features then depend on the others in its batch. What each keeps of
    an image's colour, and what each measured: docs/training.md, "Encoder statistics"."""

    def __post_init__(self) -> None:
        if self.backbone not in TRUNK_CHANNELS:
            raise DepthnerfError(f"model config: encoder.backbone must be one of {sorted(TRUNK_CHANNELS)}, "
                                 f"got {self.backbone!r}")
        if not 1 <= self.num_layers <= 4:
            raise DepthnerfError(f"model config: encoder.num_layers must be 1..4, got {self.num_layers}")
        if not (math.isfinite(self.image_scale) and self.image_scale > 0):  # inf: floor(inf) in feature_side
            raise DepthnerfError(f"model config: encoder.image_scale must be a finite number > 0, "
                                 f"got {self.image_scale}")
        if self.norm_stats not in NORM_STATS:
            raise DepthnerfError(f"model config: encoder.norm_stats must be one of {', '.join(NORM_STATS)}, "
                                 f"got {self.norm_stats!r}")
        if self.depth_channels < 1 or self.depth_hidden < 1:
            raise DepthnerfError(f"model config: encoder.depth_channels and depth_hidden must be >= 1, got "
                                 f"{self.depth_channels} and {self.depth_hidden}")

    def feature_side(self, resolution: int) -> int:
        """Side in pixels of the encoded feature maps (``Hf``) for square ``resolution`` inputs: ``image_scale``
        (floored, as ``F.interpolate`` sizes it), then conv1's ceil-halving (the deeper stages are resized up to
        it)."""
        side = math.floor(resolution * self.image_scale) if self.image_scale != 1.0 else resolution
        return -(-side // 2)

    def deepest_side(self, resolution: int) -> int:
        """Side in pixels of the deepest feature stage for square ``resolution`` inputs: :meth:`feature_side`
        (``image_scale``, conv1), then a ceil-halving for the max-pool (with more than one stage) and for each of
        layer2 and layer3 that is built (layer1 keeps its input size)."""
        side = self.feature_side(resolution)
        for _ in range(int(self.num_layers > 1 and self.use_first_pool) + max(0, self.num_layers - 2)):
            side = -(-side // 2)
        return side

    @property
    def trunk_channels(self) -> int:
        """Channels contributed by the ResNet trunk (512 for the default 4 stages)."""
        return sum(TRUNK_CHANNELS[self.backbone][: self.num_layers])

    def latent_size(self, depth_aware: bool) -> int:
        """Total feature channels C of the encoded maps: trunk + depth encoder (for a depth-aware model)."""
        return self.trunk_channels + (self.depth_channels if depth_aware else 0)


@dataclass
class FieldConfig:
    """One NeRF MLP (pixelNeRF's ResnetFC): positional encoding + residual blocks + feature injection."""

    d_hidden: int = 512
    """Width of every hidden layer."""
    n_blocks: int = 5
    """Number of residual blocks (two linear layers each, pre-activation ReLU)."""
    combine_layer: int = 3
    """Source views are mean-pooled just before this block; features are added (through one linear layer per
    block, ``lin_z``) before each of the blocks ``0 .. combine_layer-1``. ``combine_layer == n_blocks`` pools
    after the last block."""
    num_freqs: int = 6
    """Positional-encoding frequencies of the point coordinates."""
    freq_factor: float = 1.5
    """Base frequency: the encoding uses ``sin/cos(freq_factor * 2^k * x)``, k = 0..num_freqs-1."""
    include_input: bool = True
    """Prepend the raw coordinates to the encoding (3 + 6*num_freqs dims; 39 for 6 frequencies)."""
    use_viewdirs: bool = True
    """Append the unit view direction, rotated into the source camera frame, without encoding (3 dims)."""
    point_frame: Literal["rotated", "camera"] = "rotated"
    """Coordinates that are encoded: "rotated" = world point rotated into the source camera axes but not
    translated (pixelNeRF ``normalize_z=True``, its default: the object centre stays at the origin);
    "camera" = full source-camera coordinates."""
    density_bias_init: float | None = None
    """None = pixelNeRF's init of the density output (kaiming weights, zero bias). Because the pixel-aligned
    features are non-negative (post-ReLU), that init makes the density pre-activation nearly the same random
    constant at every point, negative about half the time (measured: 1% of points alive for one d_hidden=128
    seed), and a ReLU density that starts negative everywhere never receives a gradient. A float ``b`` instead
    starts the density row of ``lin_out`` at zero weights and bias ``b`` (density ``relu(b)`` everywhere),
    which always trains."""
    lin_z_on_map: bool = True
    """Apply the feature linears ``lin_z`` to the feature MAP once per source view and sample the result,
    instead of sampling features and applying ``lin_z`` per point. Bilinear sampling with border padding is an
    affine combination with weights summing to 1, so both compute the same function; the map version needs
    far fewer FLOPs whenever there are more sampled points than feature pixels."""
    chunk_points: int = 4096
    """Without autograd (inference), points per object are processed in chunks of this size to bound memory
    and keep activations cache-resident; with autograd everything is one batch."""

    def __post_init__(self) -> None:
        for name, least in (("d_hidden", 1), ("n_blocks", 1), ("chunk_points", 1), ("num_freqs", 0)):
            if getattr(self, name) < least:
                raise DepthnerfError(f"model config: field.{name} must be >= {least}, "
                                     f"got {getattr(self, name)}")
        if not 0 <= self.combine_layer <= self.n_blocks:
            raise DepthnerfError(f"model config: field.combine_layer must be in 0..n_blocks={self.n_blocks}, "
                                 f"got {self.combine_layer}")
        if not (math.isfinite(self.freq_factor) and self.freq_factor > 0):  # 0: every sin/cos a constant
            raise DepthnerfError(f"model config: field.freq_factor must be a finite number > 0, "
                                 f"got {self.freq_factor}")
        if self.point_frame not in ("rotated", "camera"):
            raise DepthnerfError(f"model config: field.point_frame must be 'rotated' or 'camera', "
                                 f"got {self.point_frame!r}")

    @property
    def d_encoding(self) -> int:
        """Width of the positional encoding of a 3D point."""
        return 3 * 2 * self.num_freqs + (3 if self.include_input else 0)

    @property
    def d_in(self) -> int:
        """Width of the MLP input (encoding + view direction): 42 for the defaults."""
        return self.d_encoding + (3 if self.use_viewdirs else 0)


@dataclass
class PixelNeRFConfig:
    """The whole network: encoder + coarse MLP + (optional separate) fine MLP."""

    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    """Image (+ depth) encoder."""
    coarse: FieldConfig = field(default_factory=FieldConfig)
    """The coarse NeRF MLP."""
    fine: FieldConfig | None = field(default_factory=FieldConfig)
    """The fine NeRF MLP, a separate network (pixelNeRF ``mlp_fine``); None = the coarse network also serves
    the fine pass (pixelNeRF with an empty ``mlp_fine``)."""
    mirror: bool = False
    """Mirror-symmetric conditioning (beyond the paper; off in the paper presets): every query point also reads
    the source features at the projection of its mirror image in the object's symmetry plane
    (:mod:`depthnerf.data.symmetry`), through its own input and feature linears (``lin_in_mirror``,
    ``lin_z_mirror``), which also get whether the point and its mirror image project inside the source frame.
    Objects without a plane (a zero plane) skip that branch, so one model serves both."""
    prior_at_point: bool = False
    """Depth prior at the point (beyond the paper; off in the paper presets; depth-aware models only): the MLP
    input also gets the normalised prior (:attr:`SourceViews.disparity <depthnerf.model.pixelnerf.SourceViews>`
    times :data:`PRIOR_POINT_SCALE`: foreground in [-0.8, 0.8], background -1) read bilinearly at the point's
    projection at the source image's full resolution, and mirror models also at the mirror image's projection.
    Next to the point's own source-frame coordinates it says whether the point lies in front of, on or behind
    the surface the input view sees (and so whether its mirror image is seen or hidden), a per-pixel cue that
    the encoder's half-resolution, convolved features blur."""
    rgb_at_point: bool = False
    """Colour at the point (beyond the paper; off in the paper presets; any model): the MLP input also gets the
    source image's RGB (mapped to [-1, 1]) read bilinearly at the point's projection at full resolution, and
    mirror models also at the mirror image's projection (after the prior column when both are on): the colour
    a visible point (or its visible mirror image) has, which the encoder's features carry only blurred."""
    global_features: bool = False
    """Global features (beyond the paper; off in the paper presets; any model): each source view's feature maps
    averaged over the image, through one more linear per MLP (``lin_global``), are added to the MLP's first
    hidden layer at every point (before the views are averaged). Pixel-aligned features describe what the input
    shows along the point's ray; this says what the whole object looks like (its colours), which a surface the
    input does not see (a chair back seen edge-on) can only get from elsewhere in the image. pixelNeRF's code has
    the same idea as a separate global encoder, unused in its SRN configuration."""

    @property
    def point_columns(self) -> int:
        """Input columns each MLP branch gets from the source pixels at a projection: 1 for the prior
        (``prior_at_point``) + 3 for the colour (``rgb_at_point``)."""
        return int(self.prior_at_point) + 3 * int(self.rgb_at_point)
