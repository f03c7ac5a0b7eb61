"""The (depth-aware) pixelNeRF module: ``encode`` source views, then query coarse/fine fields.

``encode`` returns an :class:`EncodedViews` bundle and stores nothing on the module (unlike pixelNeRF's
``encoder.latent`` buffers), so several encodings can be rendered interleaved. ``field(enc, which)`` returns a
:data:`FieldFn` closure over that bundle, which is what ``depthnerf.render.render_rays`` calls.

Per query point and source view (conventions of ``depthnerf.data.cameras``): the point is brought into the source
camera (OpenCV axes), projected with the source intrinsics, the view's feature map is sampled there
(``depthnerf.model.features``), the point's coordinates (rotated into the source camera axes, pixelNeRF's
``normalize_z``) are positionally encoded and the view direction is rotated into the source camera axes. The MLP
averages over the V source views at its combine layer (pixelNeRF's multi-view mean pooling).

Speed (figures from ``benchmarks/bench_model.py``): the MLP is one big matmul per layer over all B*V*R*S
points; ``lin_z`` is applied to the feature maps (``FieldConfig.lin_z_on_map``); features are gathered from
channels-last maps by a fused ``embedding_bag``; without autograd the residual blocks update in place and points
are chunked (``FieldConfig.chunk_points``). How a field runs at inference (autocast dtype, point chunk, a
compiled MLP forward) is a :class:`FieldRuntime` that whoever renders passes to :meth:`PixelNeRF.field`
(``depthnerf.render.precision`` makes one from a device's policy): under bf16 autocast the linears run in bf16
(about 2x faster on avx512_bf16 CPUs) while the residual stream, the sampled features and the returned rgb/sigma
stay fp32. Training runs fp32 unless its step sets autocast itself.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Literal

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from depthnerf.bundles import FieldFn, TensorBundle
from depthnerf.data.cameras import invert_pose
from depthnerf.data.symmetry import has_plane, reflect_dirs, reflect_points
from depthnerf.errors import DepthnerfError
from depthnerf.model.config import ENCODER_NORMS, PRIOR_POINT_SCALE, EncoderNorm, PixelNeRFConfig
from depthnerf.model.encoder import ImageEncoder
from depthnerf.model.features import (
    MapSamples,
    in_frame,
    map_samples,
    project_points,
    rotate_dirs,
    sample_projected,
    to_source_frames,
)
from depthnerf.model.field import MirrorQuery, ResidualField


@dataclass
class SourceViews(TensorBundle):
    """The conditioning views of B objects, V views each."""

    images: Float[Tensor, "B V 3 H W"]
    """RGB in [0, 1]."""
    poses: Float[Tensor, "B V 4 4"]
    """Camera-to-world, OpenCV axes."""
    focal: Float[Tensor, " B"]
    """Focal length in pixels (one per object, shared by its views)."""
    principal: Float[Tensor, "B 2"]
    """Principal point (cx, cy) in pixels."""
    disparity: Float[Tensor, "B V 1 H W"] | None = None
    """The depth prior's relative disparity, normalised (``depthnerf.depth.normalize.normalize_disparity``:
    foreground in [-4, 4], larger = nearer, background -5); required iff the encoder uses depth, ignored otherwise."""
    symmetry_plane: Float[Tensor, "B 4"] | None = None
    """Each object's mirror-symmetry plane in the world frame (:mod:`depthnerf.data.symmetry`; a zero row: no
    plane); read by models with ``PixelNeRFConfig.mirror``, ignored otherwise. None: no object has one."""


@dataclass
class EncodedViews(TensorBundle):
    """Everything the fields need about the source views; produced by :meth:`PixelNeRF.encode`."""

    features: Float[Tensor, "B V C Hf Wf"]
    """Pixel-aligned feature maps (C = 512, + depth channels for the depth-aware model)."""
    w2c: Float[Tensor, "B V 4 4"]
    """World-to-camera transforms (OpenCV axes)."""
    focal: Float[Tensor, " B"]
    """Focal length in pixels."""
    principal: Float[Tensor, "B 2"]
    """Principal point (cx, cy) in pixels."""
    image_size: tuple[int, int]
    """(H, W) of the source images, the frame in which (u, v) are measured."""
    symmetry_plane: Float[Tensor, "B 4"] | None = None
    """The sources' symmetry planes (:attr:`SourceViews.symmetry_plane`)."""
    point_map: Float[Tensor, "B V H W K"] | None = None
    """The source pixels read at each point's projection, channels-last at the source images' resolution
    (:meth:`PixelNeRF.point_map`; K = ``PixelNeRFConfig.point_columns``; None when K = 0)."""


@dataclass(frozen=True)
class FieldRuntime:
    """How field queries run: a device's inference settings, given to :meth:`PixelNeRF.field` by whoever renders
    (never stored on the model). The default runs the MLPs as they are, in the field config's point chunks."""

    autocast: torch.dtype | None = None
    """Without autograd, queries run under ``torch.autocast(device, this dtype)`` (None: as called)."""
    chunk_points: int | None = None
    """Without autograd, points per MLP call (None: the field config's ``chunk_points``)."""
    residual: torch.dtype | None = None
    """Without autograd, the dtype of the MLPs' residual stream (None: fp32; ``torch.bfloat16`` with bf16
    ``autocast``: :meth:`ResidualField.forward`'s ``residual_dtype``)."""
    gather_inside: bool = False
    """Without autograd, the MLP forward gets the feature maps and the points' grid coordinates
    (:class:`~depthnerf.model.features.MapSamples`) and gathers the features itself; with a compiled forward
    the gather is then in the compiled graph (``--gather inside``). False: features are sampled before the call."""
    map_dtype: torch.dtype | None = None
    """With ``gather_inside``, the dtype the maps are read in (None: fp32; ``torch.bfloat16``: half the bytes,
    the features rounded to bf16, ``--gather inside-bf16``); coordinates and corner weights stay fp32."""
    relu_epilogue: bool = False
    """Without autograd, each residual block's first linear runs with its bias and ReLU in the matrix product's
    epilogue (:func:`~depthnerf.model.field.linear_relu`; one kernel fewer per block on CUDA). Same values up to
    float rounding."""
    forwards: Mapping[str, Callable[..., Tensor]] = field(default_factory=dict)
    """What runs in place of a pass's MLP forward, by pass (``"coarse"``, ``"fine"``): e.g. a ``torch.compile``
    wrapper of it, held here by the caller (the module is not changed); a pass not listed calls its MLP."""


def _check_sources(src: SourceViews, depth_aware: bool) -> None:
    images = src.images
    if images.ndim != 5 or images.shape[2] != 3:
        raise DepthnerfError(f"SourceViews.images must be [B, V, 3, H, W], got {list(images.shape)}")
    b, v, _, h, w = images.shape
    expected = {"poses": (src.poses, (b, v, 4, 4)), "focal": (src.focal, (b,)), "principal": (src.principal, (b, 2))}
    if depth_aware:
        if src.disparity is None:
            raise DepthnerfError("SourceViews.disparity is None but the depth-aware model needs the depth prior")
        expected["disparity"] = (src.disparity, (b, v, 1, h, w))
    if src.symmetry_plane is not None:
        expected["symmetry_plane"] = (src.symmetry_plane, (b, 4))
    for name, (tensor, shape) in expected.items():
        if tuple(tensor.shape) != shape:
            raise DepthnerfError(f"SourceViews.{name} must have shape {list(shape)}, got {list(tensor.shape)}")


class PixelNeRF(nn.Module):
    """Encoder + coarse MLP + fine MLP; the baseline and the depth-aware model differ only in ``depth_aware``.

    ``depth_aware`` is derived from the depth prior (:attr:`depthnerf.depth.prior.PriorConfig.enabled`): the
    depth-aware model's encoder also takes the normalised prior.
    """

    def __init__(self, cfg: PixelNeRFConfig, *, depth_aware: bool):
        super().__init__()
        if cfg.prior_at_point and not depth_aware:
            raise DepthnerfError("model config: prior_at_point reads the depth prior, but this model has none "
                                 "(--depth none); drop --model.prior_at_point or choose a prior")
        self.cfg = cfg
        self.depth_aware = bool(depth_aware)
        """The encoder also takes the depth prior (a 4th input channel and the depth encoder)."""
        self.encoder = ImageEncoder(cfg.encoder, self.depth_aware)
        latent = cfg.encoder.latent_size(self.depth_aware)
        extra = cfg.point_columns
        self.coarse = ResidualField(cfg.coarse, latent, mirror=cfg.mirror, extra_inputs=extra,
                                    global_features=cfg.global_features)
        self.fine = (ResidualField(cfg.fine, latent, mirror=cfg.mirror, extra_inputs=extra,
                                   global_features=cfg.global_features) if cfg.fine is not None else None)

    def encode(self, src: SourceViews, *, encoder_norm: EncoderNorm = "running") -> EncodedViews:
        """Feature maps of all source views; nothing is stored on the module. ``encoder_norm`` (evaluation mode):
        the encoder's BatchNorm layers normalise with their running statistics (``"running"``, pixelNeRF) or with
        each object's own source-view statistics, as training does (``"image"``)."""
        _check_sources(src, self.depth_aware)
        if encoder_norm not in ENCODER_NORMS:
            raise DepthnerfError(f"encoder_norm must be one of {', '.join(ENCODER_NORMS)}, got {encoder_norm!r}")
        b, v, _, h, w = src.images.shape
        disparity = src.disparity.reshape(b * v, 1, h, w) if self.depth_aware else None
        feats = self.encoder(src.images.reshape(b * v, 3, h, w), disparity, objects=b,
                             image_stats=encoder_norm == "image")
        plane = src.symmetry_plane
        return EncodedViews(features=feats.reshape(b, v, *feats.shape[1:]), w2c=invert_pose(src.poses),
                            focal=src.focal.to(feats.dtype), principal=src.principal.to(feats.dtype),
                            image_size=(h, w), symmetry_plane=None if plane is None else plane.to(feats.dtype),
                            point_map=self.point_map(src))

    def point_map(self, src: SourceViews) -> Float[Tensor, "B V H W K"] | None:
        """What ``prior_at_point`` / ``rgb_at_point`` models read at each projection, channels-last: the
        normalised prior times ``PRIOR_POINT_SCALE``, then RGB mapped to [-1, 1] (None: neither option)."""
        parts = []
        if self.cfg.prior_at_point:
            parts.append(src.disparity.float() * PRIOR_POINT_SCALE)
        if self.cfg.rgb_at_point:
            parts.append(src.images.float() * 2.0 - 1.0)
        return torch.cat(parts, dim=2).permute(0, 1, 3, 4, 2).contiguous() if parts else None

    def network(self, which: Literal["coarse", "fine"]) -> ResidualField:
        """The MLP used for a pass (the coarse one for "fine" when there is no separate fine network)."""
        if which not in ("coarse", "fine"):
            raise ValueError(f"which must be 'coarse' or 'fine', got {which!r}")
        return self.fine if which == "fine" and self.fine is not None else self.coarse

    def field(self, enc: EncodedViews, which: Literal["coarse", "fine"],
              runtime: FieldRuntime | None = None) -> FieldFn:
        """The radiance field of one network conditioned on ``enc`` (a closure; no module state), run as
        ``runtime`` says (None: the default :class:`FieldRuntime`).

        With ``lin_z_on_map`` the network's feature linears are applied to the maps here, once per call.
        """
        runtime = runtime if runtime is not None else FieldRuntime()
        mlp = self.network(which)
        forward = runtime.forwards.get(which, mlp)
        b, v, c, hf, wf = enc.features.shape
        plane = enc.symmetry_plane if self.cfg.mirror else None
        gate = has_plane(plane) if plane is not None else None
        # eagerly the branch is skipped when no object has a plane; traced (``--compile-step``) it always runs, its
        # gate zeroing it per object, the same values without a host sync and a graph break on ``gate.any()``
        use_mirror = gate is not None and (torch.compiler.is_compiling() or bool(gate.any()))
        if mlp.cfg.lin_z_on_map:
            flat = enc.features.reshape(b * v, c, hf, wf)
            maps = mlp.latent_map(flat).reshape(b, v, hf, wf, -1)
            maps_m = mlp.latent_map(flat, mirror=True).reshape(b, v, hf, wf, -1) if use_mirror else None
        else:
            maps = enc.features.permute(0, 1, 3, 4, 2).contiguous()  # channels-last for row gathers
            maps_m = maps
        chunk = runtime.chunk_points or mlp.cfg.chunk_points
        if runtime.gather_inside and runtime.map_dtype is not None and not torch.is_grad_enabled():
            shared = maps_m is maps  # cast once per call of field(); inference only, as gather_inside
            maps = maps.to(runtime.map_dtype)
            maps_m = maps if shared else None if maps_m is None else maps_m.to(runtime.map_dtype)
        amp_dtype = runtime.autocast
        global_term = mlp.global_term(enc.features) if self.cfg.global_features else None
        point_map = enc.point_map if self.cfg.point_columns else None
        given = 0 if point_map is None else point_map.shape[-1]
        if given != self.cfg.point_columns:
            raise DepthnerfError(f"EncodedViews.point_map has {given} channels, this model reads the source pixels "
                                 f"at each point through {self.cfg.point_columns} (encode the views with this model)")

        def with_pixels(inputs: Tensor, uv: Tensor) -> Tensor:
            """Append the source pixels at the projections ``uv`` (``point_columns`` models; else as is)."""
            if point_map is None:
                return inputs
            return torch.cat([inputs, sample_projected(point_map, uv, enc.image_size).to(inputs.dtype)], dim=-1)

        def features(source_maps: Tensor, uv: Tensor, grad: bool) -> Tensor | MapSamples:
            """The features at projections ``uv``: sampled now, or (``gather_inside`` at inference) the maps and
            the points' grid coordinates, gathered by the MLP forward."""
            if runtime.gather_inside and not grad:
                return map_samples(source_maps, uv, enc.image_size)
            return sample_projected(source_maps, uv, enc.image_size)

        def run(points: Tensor, dirs: Tensor, grad: bool) -> Tensor:
            rotated, cam = to_source_frames(points, enc.w2c)
            coords = rotated if mlp.cfg.point_frame == "rotated" else cam
            dirs_src = rotate_dirs(dirs, enc.w2c) if mlp.cfg.use_viewdirs else None
            uv = project_points(cam, enc.focal, enc.principal)
            latent = features(maps, uv, grad)
            mirror = None
            if use_mirror:
                rotated_m, cam_m = to_source_frames(reflect_points(points, plane), enc.w2c)
                dirs_m = rotate_dirs(reflect_dirs(dirs, plane), enc.w2c) if mlp.cfg.use_viewdirs else None
                uv_m = project_points(cam_m, enc.focal, enc.principal)
                flags = torch.stack([in_frame(cam, uv, enc.image_size), in_frame(cam_m, uv_m, enc.image_size)], -1)
                inputs_m = mlp.inputs(rotated_m if mlp.cfg.point_frame == "rotated" else cam_m, dirs_m)
                inputs_m = with_pixels(torch.cat([inputs_m, flags.to(inputs_m.dtype)], dim=-1), uv_m)
                mirror = MirrorQuery(inputs=inputs_m, latent=features(maps_m, uv_m, grad), gate=gate)
            return forward(with_pixels(mlp.inputs(coords, dirs_src), uv), latent, projected=mlp.cfg.lin_z_on_map,
                           mirror=mirror, global_term=global_term,
                           residual_dtype=None if grad else runtime.residual,
                           relu_epilogue=runtime.relu_epilogue and not grad)

        def field_fn(points: Float[Tensor, "B R S 3"], dirs: Float[Tensor, "B R 3"]
                     ) -> tuple[Float[Tensor, "B R S 3"], Float[Tensor, "B R S"]]:
            nb, r, s, _ = points.shape
            if nb != b or tuple(dirs.shape) != (nb, r, 3):
                raise DepthnerfError(f"field query: points {list(points.shape)} / dirs {list(dirs.shape)} do not "
                                     f"match {b} encoded objects")
            pts = points.reshape(b, r * s, 3)
            dirs_pp = dirs[:, :, None, :].expand(b, r, s, 3).reshape(b, r * s, 3)
            grad = torch.is_grad_enabled()
            amp = (torch.autocast(points.device.type, dtype=amp_dtype) if amp_dtype is not None and not grad
                   else contextlib.nullcontext())
            with amp:
                if grad or r * s <= chunk:
                    raw = run(pts, dirs_pp, grad)
                else:
                    raw = torch.cat([run(pts[:, i:i + chunk], dirs_pp[:, i:i + chunk], grad)
                                     for i in range(0, r * s, chunk)], dim=1)
            raw = raw.to(points.dtype)  # under bf16 autocast the MLP runs in bf16; the renderer gets fp32
            return torch.sigmoid(raw[..., :3]).reshape(b, r, s, 3), F.relu(raw[..., 3]).reshape(b, r, s)

        return field_fn

    def fields(self, enc: EncodedViews, runtime: FieldRuntime | None = None) -> tuple[FieldFn, FieldFn]:
        """``(coarse, fine)`` fields for ``render_rays``."""
        return self.field(enc, "coarse", runtime), self.field(enc, "fine", runtime)
