"""The training config tree and the named presets.

One dataclass per component, a docstring under every field. The model and renderer get their own configs
(:class:`~depthnerf.model.config.PixelNeRFConfig`, :class:`~depthnerf.render.config.RenderConfig`), never this tree.
Presets are functions of the depth prior, because the paper's method and the baseline differ by one switch:
``--depth none`` builds the pixelNeRF baseline, any other estimator the depth-aware model (whether the encoder
takes the prior is derived from ``prior``, :attr:`~depthnerf.depth.prior.PriorConfig.enabled`, never stored).
:func:`check_config` rejects, when the config is built, settings no training path honours.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from depthnerf.config_io import NumberRules, broken_rule, flat_keys, from_dict, to_dict
from depthnerf.data.protocol import check_input_views
from depthnerf.data.srn import CATEGORY_DEFAULTS, category_defaults
from depthnerf.depth.prior import PriorConfig, portable_prior
from depthnerf.errors import DepthnerfError
from depthnerf.model.config import EncoderConfig, FieldConfig, PixelNeRFConfig
from depthnerf.pretrained.spec import InferenceSpec, model_config_from_dict
from depthnerf.render.config import RENDER_NUMBER_RULES, RenderConfig, SamplerConfig

DENSITY_BIAS = 0.5
"""Initial bias of the density output in every preset: with randomly initialised encoders pixelNeRF's zero bias
leaves the ReLU density dead for some seeds (measured: 3 of 10 at d_hidden 128), and a dead density never trains
(see ``FieldConfig.density_bias_init``)."""


@dataclass
class DataConfig:
    """Which images the run reads and how."""

    root: str = "data/synth"
    """Dataset root holding ``<category>_{train,val,test}/`` folders (SRN layout)."""
    category: str = "cars"
    """Folder prefix of the category (``cars`` reads ``cars_train`` ...); also picks the default z-range."""
    resolution: int = 128
    """Training image size (square); images are area-resampled and intrinsics rescaled when it differs."""
    z_near: float | None = None
    """Near bound of the ray distance; None = the category's SRN value (cars 0.8, chairs 1.25)."""
    z_far: float | None = None
    """Far bound of the ray distance; None = the category's SRN value (cars 1.8, chairs 2.75)."""
    pixel_center: float = 0.0
    """Where the dataset's pixel (row i, column j) has its centre in the coordinates of its ``intrinsics.txt``:
    ``(j + c, i + c)``. 0.0 = pixelNeRF's reading (every paper preset: faithful reproduction, half a pixel off
    Blender/SRN renders); 0.5 = Blender's convention, exact for SRN and ``depthnerf synth --framing srn`` data.
    Applied once where views are loaded (a principal-point shift, :meth:`Intrinsics.with_pixel_center`), so rays
    and feature projection agree; eval, reconstruct and the demo use the value the checkpoint was trained with.
    Must lie in ``[0, 1)`` (:func:`check_config`)."""
    symmetry_plane: tuple[float, ...] | None = None
    """The objects' mirror-symmetry plane ``nx,ny,nz,d`` in the world frame, read by mirror models
    (``--model.mirror true``) only; None = the dataset card's, else ShapeNet's left-right plane x = 0
    (:func:`depthnerf.data.symmetry.dataset_plane`, where the convention is stated)."""
    target_views: int = 0
    """Target views loaded per object and step (0 = all views but the sources, as pixelNeRF)."""
    source_views: tuple[int, ...] = (1,)
    """Source views each object is conditioned on per step, drawn at random (pixelNeRF's ``--nviews``; ``1`` = the
    paper's single view, every preset). Several counts (``--data.source_views 1,2``, pixelNeRF's ``--nviews "1 2"``)
    draw one of them per step, uniformly, the same for every object and rank of the step. The model averages the
    views' features at its MLP's ``combine_layer``; a model trained on several is evaluated on as many with
    ``depthnerf eval --input-views`` (e.g. ``64 104``). Each count once, each >= 1 (:func:`check_config`)."""
    channel_permute: float = 0.0
    """Fraction of training items whose colour channels are permuted, source views and target rays alike (one of
    the five non-identity permutations, drawn per item; white and grey stay as they are): the field then has to take
    an object's colour from its input view, not from the colours its category usually has (beyond the paper; 0 in
    every preset). Must lie in ``[0, 1]``."""
    num_workers: int = 2
    """DataLoader worker processes (0 = load in the main process)."""
    view_store: str = ""
    """Folder of the training views decoded once (:mod:`depthnerf.data.view_store`; built or brought up to date
    when training starts, reusable across runs at the same resolution); items then read only the pixels their
    rays hit instead of decoding every view of each object from PNG (the same batches, to the bit; measured in
    docs/speed.md, "The training loop's data"). "" = decode the PNG files every step."""


@dataclass
class ScheduleConfig:
    """Optimisation schedule (the paper's, scaled by preset)."""

    max_steps: int = 400_000
    """Total optimisation steps."""
    lr: float = 1e-4
    """Adam learning rate."""
    bbox_steps: int = 100_000
    """Steps of phase 1: target rays inside the object's 2D box; afterwards from the full image."""
    objects_phase1: int = 4
    """Objects per step in phase 1 (global batch, split across ranks)."""
    objects_phase2: int = 8
    """Objects per step in phase 2."""
    rays_per_object: int = 128
    """Target rays per object per step."""
    lr_decay: float = 0.995
    """Exponential learning-rate decay per epoch of phase 2 (1.0 = constant); ``lr_schedule="exponential"`` only."""
    lr_schedule: Literal["exponential", "cosine"] = "exponential"
    """``exponential``: pixelNeRF's, ``lr * lr_decay^(whole epochs of phase 2)``; ``cosine`` (beyond the paper): a
    half cosine from ``lr`` at the start of phase 2 down to ``lr_final`` at ``max_steps`` (so a ``--resume`` with a
    larger ``--max-steps`` stretches the remaining curve). Both hold ``lr`` through phase 1."""
    lr_final: float = 0.0
    """Learning rate at ``max_steps`` of the ``cosine`` schedule (0 <= lr_final <= lr)."""
    depth_loss_weight: float = 0.0
    """Weight of the scale/shift-invariant depth loss against the target view's prior (beyond the paper; 0 = off)."""
    depth_loss_min_opacity: float = 0.5
    """Foreground rays whose fine render has less opacity than this are left out of the depth loss and its
    scale/shift fit (``depthnerf.render.depth_loss``): their expected depth is undefined (an empty ray's is 0, a
    disparity outlier that would skew the fit for every other ray), and its gradient grows as 1 / opacity. In [0, 1)."""
    step_shape: Literal["batched", "per-object"] = "batched"
    """How a step runs its objects: ``batched`` = all of a rank's objects through the encoder and the fields
    together (one call each); ``per-object`` = one object at a time with gradients accumulated. Same per-object
    BatchNorm statistics and noise, so the same result up to float rounding
    (``depthnerf.train.step``); a speed choice only."""
    mirror_dropout: float = 0.2
    """Mirror models only: the fraction of training items conditioned WITHOUT their symmetry plane (drawn per item
    from the item's seed), so that one model also serves inputs without a plane (a photo whose facing is not
    given); 0 = always with the plane."""
    mirror_jitter: float = 0.0
    """Mirror models only (beyond the paper): each item's plane is turned by an angle drawn uniformly from
    [-mirror_jitter, +mirror_jitter] degrees about a random axis in the plane, so the model learns to read its
    mirror features from a plane that is a little off, as a photo's guessed facing is (docs/RESULTS.md, "Facing");
    0 = the exact plane (every preset)."""
    background_opacity_weight: float = 0.0
    """Weight of :func:`~depthnerf.train.step.background_opacity_per_object` on coarse and fine opacity of
    background target rays, averaged over objects (beyond the paper; 0 = off). On white backgrounds, white density on a background ray costs no
    colour loss; this term penalises it (the white floaters of docs/RESULTS.md). The term is measured and logged
    (``loss_background``) at every weight, 0 included."""
    foreground_opacity_weight: float = 0.0
    """Weight of :func:`~depthnerf.train.step.foreground_opacity_per_object`: squared transparency of coarse and
    fine on target rays that show the object, averaged over objects (beyond the paper; 0 = off). With the
    background term it is a silhouette loss on the target's mask; it pushes thin and light-coloured parts, whose
    colour error is small, to full opacity; measured on chairs it fattens the shapes instead (docs/RESULTS.md, "A
    foreground-opacity term"). Measured and logged (``loss_foreground``) at every weight."""
    freeze: tuple[str, ...] = ()
    """Parameter-name prefixes held fixed (beyond the paper; empty = train everything): ``encoder`` is pixelNeRF's
    ``--freeze_enc``, ``fine.lin_out,coarse.lin_out`` the output layers; a module whose parameters are all frozen
    runs in evaluation mode (BatchNorm on its running statistics, not updated). See :mod:`depthnerf.train.freeze`."""


@dataclass
class LogConfig:
    """Observability and checkpoints."""

    log_every: int = 50
    """Write a ``metrics.jsonl`` line and TensorBoard scalars every this many steps."""
    val_every: int = 2000
    """Validate (PSNR/SSIM on fixed val objects) every this many steps (0 = never)."""
    val_objects: int = 4
    """Number of fixed validation objects (the first ones of the val split)."""
    val_views: tuple[int, ...] = (0, 125, 200)
    """Target views rendered per validation object (view 64 is the input, as in the test protocol). Views other
    than these defaults (SRN's 251-view val objects) must exist in every val object; the defaults fall back to
    views an object has, with a note."""
    val_input_views: tuple[int, ...] = ()
    """Views each validation object is conditioned on, the first the primary (``64,104``: a model trained with
    ``--data.source_views 2`` validated, and its best checkpoint chosen, as pixelNeRF's two-view protocol scores
    it); empty = the protocol's input view (64; view 0 for objects with 64 views or fewer). Every val object must
    have them (checked before training starts)."""
    checkpoint_every: int = 2000
    """Write a checkpoint every this many steps (and at the end)."""
    keep_last: int = 3
    """Number of most recent checkpoints kept (plus ``best``)."""
    render_chunk: int = 4096
    """Rays per chunk when rendering full images."""


@dataclass
class TrainConfig:
    """Everything a training run is, written to ``RUN_DIR/config.json``."""

    preset: str = "custom"
    """Name of the preset this config started from."""
    seed: int = 0
    """Seed of every random choice (objects, views, rays, sample jitter, initialisation)."""
    data: DataConfig = field(default_factory=DataConfig)
    """Dataset."""
    prior: PriorConfig = field(default_factory=PriorConfig)
    """Depth prior."""
    model: PixelNeRFConfig = field(default_factory=PixelNeRFConfig)
    """Network."""
    render: RenderConfig = field(default_factory=RenderConfig)
    """Renderer."""
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    """Optimisation schedule."""
    log: LogConfig = field(default_factory=LogConfig)
    """Logging, validation and checkpoints."""
    init_from: str | None = None
    """A warm start (beyond the paper): a checkpoint (shipped name, weights file, checkpoint or run folder,
    :func:`depthnerf.pretrained.load.resolve_checkpoint`) whose network weights start the run; the step, the
    optimiser and the schedule start fresh. Its model config and prior must equal the run's (checked, naming the
    first difference). Read only when the run has no checkpoint of its own; None = random initialisation."""


def with_prior(cfg: TrainConfig, estimator: str, checkpoint: str | None = None) -> TrainConfig:
    """Switch between the baseline (``none``) and the depth-aware model; the only difference is the encoder input."""
    return dataclasses.replace(cfg, prior=PriorConfig(estimator=estimator, checkpoint=checkpoint))


NUMBER_RULES: NumberRules = {
    "seed": (0, True), "data.resolution": (8, True), "data.target_views": (0, True),
    "data.num_workers": (0, True),
    "schedule.max_steps": (1, True), "schedule.lr": (0, False), "schedule.bbox_steps": (0, True),
    "schedule.objects_phase1": (1, True), "schedule.objects_phase2": (1, True), "schedule.rays_per_object": (1, True),
    "schedule.lr_decay": (0, False), "schedule.lr_final": (0, True), "schedule.depth_loss_weight": (0, True),
    "schedule.background_opacity_weight": (0, True),
    "schedule.foreground_opacity_weight": (0, True), "schedule.mirror_dropout": (0, True), "schedule.mirror_jitter": (0, True),
    "log.log_every": (1, True),
    "log.val_every": (0, True),
    "log.val_objects": (0, True), "log.checkpoint_every": (1, True), "log.keep_last": (1, True),
    "log.render_chunk": (1, True), **RENDER_NUMBER_RULES}
"""Config path -> (bound, inclusive): the value must be ``>= bound`` (inclusive) or ``> bound``."""
NAMED_FLAGS = {"seed": "--seed", "schedule.max_steps": "--max-steps", "log.checkpoint_every": "--checkpoint-every"}
"""Config paths that have a named ``depthnerf train`` flag (the others are set as ``--section.field``)."""


def check_config(cfg: TrainConfig) -> TrainConfig:
    """``cfg`` if every setting in it is honoured by training, else a one-line :class:`DepthnerfError` (naming
    the flag, before anything is written)."""
    broken = broken_rule(cfg, NUMBER_RULES)
    if broken is not None:
        path, value, bound, inclusive = broken
        flag = NAMED_FLAGS.get(path, f"--{path}")
        raise DepthnerfError(f"{flag} must be {'>=' if inclusive else '>'} {bound:g}, got {value}")
    encoder = cfg.model.encoder
    if encoder.deepest_side(cfg.data.resolution) < 2:  # one value per channel: per-object BatchNorm cannot train
        least = next(r for r in range(cfg.data.resolution, 4096) if encoder.deepest_side(r) >= 2)
        raise DepthnerfError(f"--data.resolution must be >= {least} with this encoder, got {cfg.data.resolution}: "
                             f"its deepest stage would be 1x1 pixel, and training normalises each object's features "
                             f"over their pixels (BatchNorm per object)")
    counts = cfg.data.source_views
    if not counts or min(counts) < 1 or len(set(counts)) != len(counts):
        raise DepthnerfError(f"--data.source_views must list source-view counts >= 1, each once (e.g. 1 or 1,2), "
                             f"got {','.join(map(str, counts)) or 'nothing'}")
    if cfg.schedule.lr_final > cfg.schedule.lr:
        raise DepthnerfError(f"--schedule.lr_final must be <= --schedule.lr ({cfg.schedule.lr:g}), got "
                             f"{cfg.schedule.lr_final:g}")
    if not cfg.schedule.lr_decay <= 1:  # > 0 by NUMBER_RULES; above 1 the rate would grow every epoch
        raise DepthnerfError(f"--schedule.lr_decay must be in (0, 1] (1 keeps the rate constant), got "
                             f"{cfg.schedule.lr_decay:g}")
    if not 0 <= cfg.data.channel_permute <= 1:  # NaN fails too
        raise DepthnerfError(f"--data.channel_permute must be in [0, 1], got {cfg.data.channel_permute}")
    if not 0 <= cfg.schedule.depth_loss_min_opacity < 1:  # NaN fails too; 1 would leave no ray
        raise DepthnerfError(f"--schedule.depth_loss_min_opacity must be in [0, 1), got "
                             f"{cfg.schedule.depth_loss_min_opacity}")
    if cfg.schedule.mirror_dropout >= 1:
        raise DepthnerfError(f"--schedule.mirror_dropout must be < 1, got {cfg.schedule.mirror_dropout}")
    if not cfg.schedule.mirror_jitter <= 90:  # NaN fails too
        raise DepthnerfError(f"--schedule.mirror_jitter must be an angle in [0, 90] degrees, got "
                             f"{cfg.schedule.mirror_jitter}")
    if not 0 <= cfg.data.pixel_center < 1:  # NaN fails too
        raise DepthnerfError(f"--data.pixel_center must be in [0, 1) (a principal-point shift of a fraction of a "
                             f"pixel: 0.0 = pixelNeRF's reading, 0.5 = Blender's), got {cfg.data.pixel_center}")
    near, far = cfg.data.z_near, cfg.data.z_far
    if (near is not None and far is not None) or cfg.data.category in CATEGORY_DEFAULTS:
        near, far = z_range(cfg)  # an unset bound is the category's (an unknown category fails later, naming it)
        if not 0 <= near < far:
            unset = " (an unset one is the category's SRN value)" if None in (cfg.data.z_near, cfg.data.z_far) else ""
            raise DepthnerfError(f"--data.z_near / --data.z_far must satisfy 0 <= z_near < z_far, got {near}, "
                                 f"{far}{unset}")
    for path, value in flat_keys(to_dict(cfg)).items():  # inf, or NaN where no rule above would train nonsense or fail mid-run
        if isinstance(value, float) and not math.isfinite(value):
            raise DepthnerfError(f"{NAMED_FLAGS.get(path, f'--{path}')} must be a finite number, got {value}")
    if cfg.log.val_every > 0:  # validation would score nothing, or fall back to a view nobody asked for
        without = "with --log.val_every > 0 (pass --log.val_every 0 to train without validation)"
        if cfg.log.val_objects < 1:
            raise DepthnerfError(f"--log.val_objects must be >= 1 {without}, got {cfg.log.val_objects}")
        if not cfg.log.val_views or min(cfg.log.val_views) < 0:
            raise DepthnerfError(f"--log.val_views must name at least one view index >= 0 {without}, got "
                                 f"{list(cfg.log.val_views)}")
        if cfg.log.val_input_views:
            check_input_views(cfg.log.val_input_views, "--log.val_input_views")
    if cfg.render.guided.enabled:
        raise DepthnerfError("--render.guided.enabled: depth-guided sampling is an inference-time renderer "
                             "(depthnerf eval/reconstruct --guided); training renders with the paper's sampler")
    return cfg


def _paper(category: str) -> TrainConfig:
    """The paper's settings at 128x128 (pixelNeRF SRN defaults; for GPUs)."""
    live = FieldConfig(density_bias_init=DENSITY_BIAS)
    return TrainConfig(preset=f"paper-{category}", data=DataConfig(root="data/srn", category=category,
                                                                   resolution=128, num_workers=8),
                       prior=PriorConfig(estimator="depth-anything-v2"),
                       model=PixelNeRFConfig(coarse=live, fine=live),
                       render=RenderConfig(), schedule=ScheduleConfig(), log=LogConfig())


CPU_BACKGROUND_OPACITY_WEIGHT = 0.02
"""The CPU presets' background-opacity weight (beyond the paper; the paper presets keep 0): without it the
depth-aware car model grows white density on background rays (docs/RESULTS.md, "Floaters")."""


def _cpu(category: str) -> TrainConfig:
    """Sized for a 2-core CPU in <= 45 minutes (each reduction documented in docs/presets.md)."""
    small_field = FieldConfig(d_hidden=64, n_blocks=5, combine_layer=3, density_bias_init=DENSITY_BIAS)
    return TrainConfig(
        preset=f"cpu-{category}",
        data=DataConfig(root="data/synth", category=category, resolution=64, target_views=0, num_workers=1),
        prior=PriorConfig(estimator="bundled"),
        model=PixelNeRFConfig(encoder=EncoderConfig(backbone="resnet18"), coarse=small_field, fine=small_field),
        render=RenderConfig(sampler=SamplerConfig(n_coarse=32, n_importance=16, n_gaussian=8)),
        schedule=ScheduleConfig(max_steps=2000, bbox_steps=500, objects_phase1=4, objects_phase2=4,
                                rays_per_object=128, lr=1e-4 * 3, lr_decay=0.995,
                                background_opacity_weight=CPU_BACKGROUND_OPACITY_WEIGHT),
        log=LogConfig(log_every=25, val_every=250, val_objects=4, val_views=(0, 125, 200),
                      checkpoint_every=250, keep_last=2, render_chunk=4096),
    )


PRESETS: dict[str, Callable[[], TrainConfig]] = {
    "paper-cars": lambda: _paper("cars"),
    "paper-chairs": lambda: _paper("chairs"),
    "cpu-cars": lambda: _cpu("cars"),
    "cpu-chairs": lambda: _cpu("chairs"),
}
"""Named presets; each in a baseline and a depth-aware form through :func:`with_prior`."""


def preset(name: str) -> TrainConfig:
    """The config of a named preset (a fresh copy)."""
    try:
        return PRESETS[name]()
    except KeyError:
        raise DepthnerfError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}") from None


def from_dict_config(data: dict[str, Any], where: str = "config.json") -> TrainConfig:
    """A :class:`TrainConfig` from ``config.json`` (strict: unknown keys are an error).

    Configs written before the model's depth-awareness was derived from the prior hold
    ``model.encoder.use_depth``: accepted when it agrees with ``prior`` and dropped
    (:func:`depthnerf.pretrained.spec.model_config_from_dict`). Configs written before ``data.source_views`` took
    several counts hold one number ``n``: read as ``[n]``.
    """
    if not isinstance(data, dict):
        raise DepthnerfError(f"{where}: expected a mapping for TrainConfig")
    data = copy.deepcopy(data)
    section = data.get("data")
    if isinstance(section, dict) and type(section.get("source_views")) is int:  # bool is no count
        section["source_views"] = [section["source_views"]]
    prior = from_dict(PriorConfig, data.get("prior", {}), where=f"{where}.prior")
    model = data.pop("model", None)
    cfg = from_dict(TrainConfig, data, where=where)
    if model is not None:
        cfg.model = model_config_from_dict(model, prior.enabled, f"{where}.model")
    return cfg


def z_range(cfg: TrainConfig) -> tuple[float, float]:
    """(near, far) of the run: explicit config values, else the category's SRN values (read it from the
    :class:`InferenceSpec` everywhere else)."""
    if cfg.data.z_near is not None and cfg.data.z_far is not None:
        return cfg.data.z_near, cfg.data.z_far
    d = category_defaults(cfg.data.category)
    near, far = cfg.data.z_near, cfg.data.z_far  # 0.0 is a bound like any other, not "unset"
    return (d.z_near if near is None else near), (d.z_far if far is None else far)


def inference_spec(cfg: TrainConfig, prior_weights_hash: str | None = None, framing: str | None = None
                   ) -> InferenceSpec:
    """What a checkpoint of this run stores so that evaluation and reconstruction never read the training config
    (``framing``: the training data's, :func:`depthnerf.data.synth.framing.dataset_framing`); the prior names its
    weights portably (:func:`~depthnerf.depth.prior.portable_prior`)."""
    near, far = z_range(cfg)
    return InferenceSpec(model=cfg.model, render=cfg.render, prior=portable_prior(cfg.prior, prior_weights_hash),
                         category=cfg.data.category, resolution=cfg.data.resolution, z_near=near, z_far=far,
                         pixel_center=cfg.data.pixel_center, framing=framing,
                         prior_weights_hash=prior_weights_hash, preset=cfg.preset)
