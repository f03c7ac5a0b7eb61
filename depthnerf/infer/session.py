"""The inference session: a checkpoint and the caller's overrides, resolved once, for everything after training.

``InferenceSession(checkpoint, SessionOptions(...))`` loads the checkpoint (:func:`depthnerf.pretrained.load
.load_pretrained`) and resolves, once:

spec
    :attr:`InferenceSession.spec`, the checkpoint's :class:`~depthnerf.pretrained.spec.InferenceSpec` with the
    overrides applied: the prior (:func:`resolve_prior`: ``--depth`` / ``--depth-checkpoint`` through
    :meth:`PriorConfig.override <depthnerf.depth.prior.PriorConfig.override>`, checked against the model), the
    pixel centre (``--pixel-center``), the render config with the sampler's counts (``--samples``) and the guided
    request (``--guided``), and the framing
    (stated by the spec, or derived at load for older checkpoints). The stored spec stays ``pretrained.spec``.
prior source
    :attr:`InferenceSession.prior_source` of the resolved prior, by what the inputs are
    (:attr:`SessionOptions.inputs`): ``dataset`` reads the dataset's prior cache at the training resolution
    (``depthnerf eval``); ``photos`` runs the estimator live on photos (``Reconstructor``, the app); ``views``
    runs it live on dataset-like views and rounds its output as the cache stores it, so the model sees what
    ``depthnerf eval`` feeds it (the demo; ``oracle`` reads their ground-truth depth). Its weights are checked
    against the ones the model was trained with (:func:`~depthnerf.depth.prior.weights_mismatch`): other
    weights are an error, or a warning when ``--depth-checkpoint`` asked for them.
device policy
    :attr:`InferenceSession.policy` (:func:`~depthnerf.render.precision.inference_policy` of the device: bf16
    autocast, large ray chunks and point chunks on CUDA, fp32, 4096 rays and 16,384 points on the CPU; ``fp32`` /
    ``compile`` flags), the :class:`~depthnerf.model.pixelnerf.FieldRuntime` it makes (:attr:`runtime`, built
    once: it holds the compiled MLP forwards with ``compile``) and the rays per pass (:attr:`chunk`:
    ``SessionOptions.chunk``, else the policy's). Explicit arguments of every render call, never state on the model.
guided setup
    ``spec.render.guided``: the caller's :class:`~depthnerf.render.config.GuidedConfig` (None: the checkpoint's own
    sampler); :meth:`render` builds each object's source guide from it.

``depthnerf eval`` (:mod:`depthnerf.eval.protocol`, with :func:`depthnerf.eval.objects.prepare_object`),
:class:`~depthnerf.reconstruct.Reconstructor` (``depthnerf reconstruct``, the Python API, the app) and the demo
are thin users: they encode with :meth:`encode` / :meth:`encode_views`, render with :meth:`render` and mesh with
:meth:`mesh`. Training validation renders the model being trained with the spec training writes; it has no
checkpoint and no overrides, so it takes no session.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
import trimesh
from jaxtyping import Bool, Float

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.srn import ObjectRecord, ObjectViews, load_object
from depthnerf.data.symmetry import dataset_plane
from depthnerf.depth.estimators import PHOTO_ESTIMATORS
from depthnerf.depth.prior import PriorConfig, PriorSource, open_prior, weights_mismatch
from depthnerf.distributed import pick_device
from depthnerf.errors import DepthnerfError, UsageWarning
from depthnerf.model.conditioning import Conditioned, condition, condition_views
from depthnerf.model.config import ENCODER_NORMS, EncoderNorm
from depthnerf.model.pixelnerf import EncodedViews, SourceViews
from depthnerf.pretrained.load import Pretrained, load_pretrained
from depthnerf.pretrained.spec import InferenceSpec
from depthnerf.render.config import GuidedConfig
from depthnerf.render.mesh import MeshConfig, input_camera_mesh
from depthnerf.render.mesh_level import MeshLevel
from depthnerf.render.photo_colors import PhotoView
from depthnerf.render.precision import InferencePolicy, check_precision_flags, field_runtime, inference_policy
from depthnerf.render.source_guide import as_guided, make_source_guide
from depthnerf.render.views import ViewRenders, render_poses

Inputs = Literal["photos", "views", "dataset"]
"""What the session's source views are (:attr:`SessionOptions.inputs`)."""
CHECKPOINT_SAMPLER: Any = object()
"""``render(guided=...)`` default: the session's guided setup."""


@dataclass(frozen=True)
class SessionOptions:
    """The caller's overrides of what a checkpoint says about itself (None: the checkpoint's / the device's)."""

    device: str | torch.device = "cpu"
    """Torch device of the model and of rendering."""
    depth: str | None = None
    """``--depth``: another estimator for the prior (a depth-aware checkpoint only); None: the checkpoint's."""
    depth_checkpoint: str | None = None
    """``--depth-checkpoint``: other estimator weights; None: the checkpoint's when the estimator is its own."""
    inputs: Inputs = "photos"
    """Where the prior comes from: ``photos`` (live estimator; a prior that runs on photos), ``views`` (live,
    rounded as the cache stores it; ``oracle`` reads the views' depth) or ``dataset`` (the prior cache of
    :attr:`data_root`)."""
    data_root: str | Path | None = None
    """Dataset root whose prior cache serves ``dataset`` inputs."""
    records: Sequence[ObjectRecord] = ()
    """Objects the ``dataset`` prior cache must hold (checked up front)."""
    fp32: bool = False
    """Render in fp32 where the device's policy would use bf16 autocast (``--fp32``)."""
    compile: bool = False
    """``torch.compile`` the field MLPs (``--compile``)."""
    compile_mode: str | None = None
    """``--compile-mode``: the ``torch.compile`` mode (implies :attr:`compile`); None: torch's default."""
    bf16_residual: bool = False
    """``--bf16-residual``: keep the MLPs' residual stream in bf16 under CUDA's bf16 autocast."""
    gather: str = "before"
    """``--gather``: where the fields gather their features (:data:`~depthnerf.render.config.GATHERS`)."""
    chunk: int | None = None
    """Rays per render pass (``--chunk``); None: the device policy's."""
    guided: GuidedConfig | int | bool | None = None
    """Depth-guided sampling (``--guided [BUDGET]``): a budget (samples per occupied ray), True for the default
    budget or a :class:`GuidedConfig` (:func:`~depthnerf.render.source_guide.as_guided`); None: the checkpoint's
    own sampler."""
    samples: tuple[int, int, int] | None = None
    """``--samples C I G``: samples per ray of the checkpoint's coarse-to-fine sampler at inference, ``C`` coarse,
    ``I`` importance and ``G`` Gaussian ones (``render.sampler``'s ``n_coarse``, ``n_importance``, ``n_gaussian``)
    instead of those it was trained with; None: the checkpoint's."""
    pixel_center: float | None = None
    """``--pixel-center``: read data with another pixel-centre convention; None: the checkpoint's."""
    policy: InferencePolicy | None = None
    """The device policy itself (e.g. another device's, simulated); None: the policy of :attr:`device` with
    :attr:`fp32`, :attr:`compile`, :attr:`compile_mode`, :attr:`bf16_residual` and :attr:`gather`."""
    encoder_norm: EncoderNorm = "running"
    """``--encoder-norm``: the encoder's BatchNorm statistics at inference, ``running`` (pixelNeRF) or the input
    ``image``'s own, as training normalises each object (:meth:`PixelNeRF.encode`)."""
    symmetry: bool = True
    """Mirror models on ``dataset`` inputs: condition on the dataset's symmetry plane (:meth:`dataset_symmetry`);
    False (``--no-symmetry``): on none, the model's no-plane mode."""
    symmetry_plane: tuple[float, ...] | None = None
    """``--symmetry-plane``: this plane ``nx,ny,nz,d`` instead of the dataset's."""

    def __post_init__(self) -> None:
        """One line naming the flag when a value cannot work (checked before anything loads)."""
        pick_device(self.device, flag="device", auto=False)  # one line for a device this process lacks
        if self.chunk is not None and self.chunk < 1:
            raise DepthnerfError(f"--chunk must be >= 1, got {self.chunk}")
        if self.policy is None:  # a flag combination the device cannot run fails here, not after loading
            check_precision_flags(self.device, fp32=self.fp32, compile_mode=self.compile_mode,
                                  bf16_residual=self.bf16_residual, gather=self.gather)
        if self.encoder_norm not in ENCODER_NORMS:
            raise DepthnerfError(f"--encoder-norm must be one of {', '.join(ENCODER_NORMS)}, "
                                 f"got {self.encoder_norm!r}")
        check_samples(self.samples)
        if self.inputs not in ("photos", "views", "dataset"):
            raise DepthnerfError(f"SessionOptions.inputs must be photos, views or dataset, got {self.inputs!r}")

    def device_policy(self) -> InferencePolicy:
        """:attr:`policy`, or the policy of :attr:`device` with these options' flags."""
        return self.policy or inference_policy(self.device, fp32=self.fp32, compile=self.compile,
                                               compile_mode=self.compile_mode, bf16_residual=self.bf16_residual,
                                               gather=self.gather)


def check_samples(samples: Sequence[int] | None) -> None:
    """Refuse ``--samples`` counts the sampler cannot take, in one line: three counts, coarse >= 2 (the importance
    samples are drawn over the coarse bins), importance and Gaussian >= 0."""
    if samples is not None and (len(samples) != 3 or samples[0] < 2 or min(samples[1:]) < 0):
        raise DepthnerfError(f"--samples takes three counts, coarse >= 2, importance >= 0 and Gaussian >= 0, got "
                             f"{' '.join(map(str, samples))}")


def resolve_prior(trained: PriorConfig, depth: str | None, depth_checkpoint: str | None, *, photos: bool,
                  where: str) -> PriorConfig:
    """The prior a session feeds a model trained with ``trained``: the override rule
    (:meth:`PriorConfig.override <depthnerf.depth.prior.PriorConfig.override>`), then what the model and the inputs
    allow, one line naming the fix otherwise (``where``: how the checkpoint was named)."""
    prior = trained.override(depth, depth_checkpoint)
    if not trained.enabled:
        if prior.enabled or depth_checkpoint:
            flag = f"--depth {prior.estimator}" if prior.enabled else "--depth-checkpoint"
            raise DepthnerfError(f"{where}: a baseline checkpoint (trained without a depth prior) takes no depth "
                                 f"prior; drop {flag}, or use a depth-aware checkpoint")
        return trained
    if not prior.enabled:
        raise DepthnerfError(f"{where}: depth-aware checkpoint needs a depth prior; pass --depth "
                             f"{' or '.join(PHOTO_ESTIMATORS)}, not 'none'")
    if photos and prior.estimator not in PHOTO_ESTIMATORS:
        raise DepthnerfError(f"{where}: the '{prior.estimator}' prior needs ground-truth depth, which a photo "
                             f"does not have; pass --depth {' or '.join(PHOTO_ESTIMATORS)}")
    return prior


@dataclass
class EncodedView:
    """The source views of one object (one photo; V dataset views with ``eval --input-views``) conditioned on their
    prior and encoded: what every rendering of the object starts from. Renders and meshes read every view's
    features; the sampler's guide, the mesh's box and level and its photo colours read the primary (first) view."""

    inputs: SourceViews
    """What the encoder saw (images, cameras, normalised disparity of the V views), on the device."""
    disparity: Float[torch.Tensor, "1 H W"] | None
    """Raw relative disparity the prior source served for the primary view (None: no prior)."""
    enc: EncodedViews
    """The model's features of the V views."""
    pose: Float[torch.Tensor, "4 4"]
    """Camera-to-world pose of the primary view."""
    intr: Intrinsics
    """Its intrinsics (the training resolution; every view's)."""
    mask: Bool[torch.Tensor, "1 H W"]
    """The primary view's foreground mask."""


def photo_view(encoded: EncodedView) -> PhotoView:
    """The encoded view's photo, mask, camera and mirror plane as the ``photo`` mesh colour rule reads them."""
    plane = encoded.inputs.symmetry_plane
    return PhotoView(image=encoded.inputs.images[0, 0].permute(1, 2, 0).float().cpu().numpy(),
                     mask=encoded.mask[0].cpu().numpy(), c2w=encoded.pose.double().cpu().numpy(), intr=encoded.intr,
                     plane=None if plane is None else plane[0].double().cpu().numpy())


class InferenceSession:
    """A loaded checkpoint with its spec, prior source, device policy and guided setup resolved (module
    docstring)."""

    def __init__(self, checkpoint: str | Path | Pretrained, options: SessionOptions | None = None) -> None:
        options = options or SessionOptions()
        self.options = options
        self.device = torch.device(options.device)
        if isinstance(checkpoint, Pretrained):
            self.pretrained, self.name = checkpoint, str(checkpoint.path)
            checkpoint.model.to(self.device)
        else:
            self.pretrained, self.name = load_pretrained(checkpoint, self.device), str(checkpoint)
        trained = self.pretrained.spec
        if options.inputs == "dataset" and options.data_root is None:
            raise DepthnerfError("a session on dataset inputs needs the dataset root (SessionOptions.data_root)")
        prior = resolve_prior(trained.prior, options.depth, options.depth_checkpoint,
                              photos=options.inputs == "photos", where=self.name)
        guided = as_guided(options.guided)
        render = trained.render
        if guided is not None:
            render = dataclasses.replace(render, guided=dataclasses.replace(guided, enabled=True))
        if options.samples is not None:
            counts = dict(zip(("n_coarse", "n_importance", "n_gaussian"), options.samples, strict=True))
            render = dataclasses.replace(render, sampler=dataclasses.replace(render.sampler, **counts))
        self.spec = dataclasses.replace(
            trained, prior=prior,
            prior_weights_hash=trained.prior_weights_hash if prior == trained.prior else None,
            pixel_center=trained.pixel_center if options.pixel_center is None else options.pixel_center,
            render=render)
        """The resolved spec (module docstring); ``pretrained.spec`` is the checkpoint's own."""
        self.policy = options.policy or options.device_policy()
        self.chunk = options.chunk or self.policy.ray_chunk
        self.runtime = field_runtime(self.model, self.policy)
        self.prior_source = self._open_prior(options)
        self._check_prior_weights(trained, options)

    def _check_prior_weights(self, trained: InferenceSpec, options: SessionOptions) -> None:
        if self.spec.prior.estimator != trained.prior.estimator:
            return  # another prior altogether (an ablation): nothing to compare
        mismatch = weights_mismatch(self.prior_source, trained.prior_weights_hash, self.name)
        if mismatch is None:
            return
        if options.depth_checkpoint is None:
            raise DepthnerfError(f"{mismatch}; pass --depth-checkpoint with the weights it was trained on")
        warnings.warn(f"{mismatch}: --depth-checkpoint feeds the model other priors than it was trained on",
                      UsageWarning, stacklevel=3)

    def _open_prior(self, options: SessionOptions) -> PriorSource:
        if options.inputs == "dataset":
            return open_prior(self.spec.prior, data_root=options.data_root, resolution=self.spec.resolution,
                              records=options.records)
        return open_prior(self.spec.prior, device=str(self.device), match_cache=options.inputs == "views")

    @property
    def model(self):
        """The network (eval mode, on the device)."""
        return self.pretrained.model

    @property
    def guided(self) -> GuidedConfig | None:
        """The guided setup (None: the checkpoint's own sampler)."""
        return self.spec.render.guided if self.spec.render.guided.enabled else None

    @property
    def framing(self) -> str:
        """Framing of the training data (``spec.framing``)."""
        return str(self.spec.framing)

    @property
    def framing_origin(self) -> str:
        """Where the framing was read (``Pretrained.framing_origin``)."""
        return self.pretrained.framing_origin

    def provenance(self) -> dict[str, Any]:
        """The checkpoint's provenance as outputs record it."""
        pre = self.pretrained
        return {"checkpoint": str(pre.path.resolve()), "checkpoint_sha256": pre.sha256, "checkpoint_step": pre.step,
                "preset": pre.spec.preset}

    def load_views(self, record: ObjectRecord, views: Sequence[int], resolution: int, *,
                   with_depth: bool = False) -> ObjectViews:
        """Views of a dataset object at ``resolution``, read with the session's pixel centre."""
        return load_object(record, views, resolution=resolution, with_depth=with_depth,
                           pixel_center=self.spec.pixel_center)

    def dataset_symmetry(self, category: str) -> tuple[tuple[float, ...] | None, str]:
        """The symmetry plane a mirror model gets on the dataset's objects (:attr:`SessionOptions.symmetry`,
        :attr:`SessionOptions.symmetry_plane`, else :func:`~depthnerf.data.symmetry.dataset_plane`) and a line
        saying where it came from; None for other models or with ``symmetry`` off."""
        if not self.model.cfg.mirror:
            return None, "not a mirror model"
        if not self.options.symmetry:
            return None, "off (--no-symmetry)"
        if self.options.symmetry_plane is None and self.options.data_root is None:
            raise DepthnerfError("a mirror model on dataset views needs the dataset root or a symmetry plane")
        return dataset_plane(self.options.data_root or ".", category, self.options.symmetry_plane, "--symmetry-plane")

    @torch.no_grad()
    def encode(self, image: Float[torch.Tensor, "1 3 H W"], mask: Bool[torch.Tensor, "1 H W"],
               pose: Float[torch.Tensor, "4 4"], intr: Intrinsics, *,
               depth: Float[torch.Tensor, "1 H W"] | None = None,
               symmetry_plane: Sequence[float] | None = None) -> EncodedView:
        """Condition one view on the prior source and encode it (``depth``: its ground-truth z-depth, which only
        the ``oracle`` prior reads and only synthetic data has; ``symmetry_plane``: the object's mirror plane,
        read by mirror models)."""
        return self._encoded(condition(self.prior_source, image, mask, pose[None], intr, self.device, depths=depth,
                                       symmetry_plane=symmetry_plane), pose, intr, mask)

    @torch.no_grad()
    def encode_views(self, source: ObjectViews, symmetry_plane: Sequence[float] | None = None) -> EncodedView:
        """:meth:`encode` on loaded dataset views, the first the primary one (the prior source may look each up by
        its object and view)."""
        cond = condition_views(self.prior_source, source, self.device, symmetry_plane=symmetry_plane)
        return self._encoded(cond, source.poses[0], source.intrinsics, source.masks[:1])

    def _encoded(self, cond: Conditioned, pose, intr: Intrinsics, mask) -> EncodedView:
        return EncodedView(inputs=cond.inputs, disparity=None if cond.disparity is None else cond.disparity[:1],
                           enc=self.model.encode(cond.inputs, encoder_norm=self.options.encoder_norm),
                           pose=pose, intr=intr, mask=mask)

    @torch.no_grad()
    def render(self, encoded: EncodedView, poses: Float[torch.Tensor, "N 4 4"], intr: Intrinsics, *,
               guided: GuidedConfig | None = CHECKPOINT_SAMPLER, chunk: int | None = None,
               on_group: Callable[[int], Any] | None = None) -> ViewRenders:
        """Render ``poses`` of an encoded view at ``intr`` (CPU float tensors) under the device policy, depth-guided
        when the session (or ``guided``, for this call) says so; ``chunk``: rays per pass (None: the session's)."""
        guided = self.guided if guided is CHECKPOINT_SAMPLER else guided
        chunk = chunk or self.chunk
        spec, model = self.spec, self.model
        near, far = spec.z_range
        render, guide = spec.render, None
        if guided is not None:
            render = dataclasses.replace(spec.render, guided=dataclasses.replace(guided, enabled=True))
            disparity = None if encoded.disparity is None else encoded.disparity.to(self.device)
            guide = make_source_guide(model.field(encoded.enc, "coarse", self.runtime),
                                      encoded.pose[None].to(self.device), encoded.intr, near, far, disparity,
                                      encoded.mask.to(self.device), render, render.guided, chunk)
        elif render.guided.enabled:
            render = dataclasses.replace(render, guided=dataclasses.replace(render.guided, enabled=False))
        return render_poses(model, encoded.enc, poses, intr, near, far, render, chunk, self.device, on_group, guide,
                            self.runtime)

    @torch.no_grad()
    def mesh(self, encoded: EncodedView, cfg: MeshConfig, *, colored: bool = True
             ) -> tuple[trimesh.Trimesh, MeshLevel | None]:
        """Marching cubes over the encoded view's frustum box at the run's z-range (:mod:`depthnerf.render.mesh`)."""
        near, far = self.spec.z_range
        return input_camera_mesh(self.model, encoded.enc, encoded.pose, encoded.intr, near, far, cfg, self.device,
                                 colored=colored, runtime=self.runtime, mask=encoded.mask[0].cpu().numpy(),
                                 photo=photo_view(encoded) if colored else None)
