"""Configuration of the renderer: the paper's hierarchical sampler and the optional depth-guided sampling.

Defaults reproduce pixelNeRF / the paper (64 stratified coarse samples, 16 importance + 16 Gaussian fine samples,
white background, no sigma noise); every extension is a flag that is OFF by default.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")
"""``torch.compile`` modes of the field MLPs at inference (``--compile-mode``; inductor's own names):
:func:`depthnerf.render.precision.field_runtime` compiles with the one a policy names."""
GATHERS = ("before", "inside", "inside-bf16")
"""Where the field's pixel-aligned features are gathered at inference (``--gather``): ``before`` the MLP
call (``grid_sample`` on CUDA, the fused ``embedding_bag`` on the CPU); ``inside`` the MLP forward, from
the fp32 maps (under ``--compile`` inside the compiled graph: index loads of whole channel rows in inductor's
kernels); ``inside-bf16`` the same from maps rounded to bf16 (half the bytes read; coordinates and weights fp32).
Same values but for float rounding (``inside-bf16``: the features' bf16 rounding). ``inside*`` implies
``--compile``."""

RENDER_NUMBER_RULES: dict[str, tuple[float, bool]] = {
    "render.sampler.n_coarse": (1, True), "render.sampler.n_importance": (0, True),
    "render.sampler.n_gaussian": (0, True), "render.sampler.gaussian_std": (0, True),
    "render.sampler.pdf_epsilon": (0, True)}
"""The sampler's bounds (``depthnerf.config_io.NumberRules``), as paths from a config holding a ``render`` field:
training checks them on its config, loading on a checkpoint's inference spec."""


@dataclass
class SamplerConfig:
    """The paper's coarse-to-fine sampler (pixelNeRF ``NeRFRenderer`` with ``n_fine_depth``)."""

    n_coarse: int = 64
    """Stratified samples per ray between near and far, evaluated by the coarse network."""
    n_importance: int = 16
    """Inverse-CDF samples from the coarse weights over the coarse bins (pixelNeRF ``n_fine - n_fine_depth``)."""
    n_gaussian: int = 16
    """Samples from a Gaussian at the coarse expected depth, clamped to [near, far] (pixelNeRF ``n_fine_depth``)."""
    gaussian_std: float = 0.01
    """Standard deviation of the Gaussian samples, in ray-distance units (pixelNeRF ``depth_std``)."""
    pdf_epsilon: float = 1e-5
    """Added to the detached coarse weights before normalising them into a pdf (pixelNeRF's value)."""
    detach_gaussian_center: bool = False
    """Detach the coarse depth that centres the Gaussian samples. pixelNeRF does not, so the fine loss reaches
    the coarse network through the Gaussian sample positions; True stops that gradient."""
    eval_random: bool = False
    """Draw random samples at evaluation as pixelNeRF does (its sampler jitters in eval too). False (default)
    makes evaluation deterministic: bin midpoints, quantile importance samples, normal-quantile Gaussian samples."""

    @property
    def counts(self) -> tuple[int, int, int]:
        """``(n_coarse, n_importance, n_gaussian)``: the samples per ray of each kind (what ``--samples`` sets)."""
        return self.n_coarse, self.n_importance, self.n_gaussian


DEFAULT_BUDGET = 48
"""Samples per occupied ray of ``--guided`` without a number: the smallest budget measured to cost at most 0.1 dB of
PSNR against the shipped CPU checkpoints' own sampler (cars -0.08, chairs -0.04 dB; docs/RESULTS.md). The default
pass counts below (8 + 16 + 16 + 8) are this budget split 1:2:2:1."""


@dataclass
class GuidedConfig:
    """Depth-guided sampling (beyond the paper), the one config of all three of its steps
    (:mod:`depthnerf.render.source_guide`): the source view's prior aligned to metric depth (``align_*``), a
    per-ray guess of each target ray's surface from it (:mod:`depthnerf.render.depth_guide`: ``march_*``,
    ``spread``, ``surface_tolerance``, ``mask_dilation``) and the two-pass sampler around the guesses
    (:mod:`depthnerf.render.guided_sampler`: the ``n_*`` counts).

    The sampler: two passes of one network (the fine one by default), the second reusing the first's evaluations:

    - pass 1, rays the guide marks *occupied*: ``n_uniform`` stratified samples over [near, far] plus ``n_window``
      stratified over the guide's window (``[min(t_enter, t_guess - spread), t_guess + spread]`` for a trusted
      surface guess, ``[t_enter, far]`` otherwise: :meth:`~depthnerf.render.depth_guide.DepthGuide.window`); rays
      the source view sees as empty: ``n_empty`` stratified samples.
    - pass 2: ``n_importance`` (empty rays: ``n_empty_importance``) inverse-CDF samples from the pass-1 weights
      over the gaps between pass-1 samples, plus ``n_gaussian`` (occupied rays only) around the pass-1
      opacity-normalised depth; the result composites the sorted union.

    Network evaluations per ray: 48 (occupied) or 24 (empty) by default, against the paper's 64 + 96 = 160.
    ``--guided BUDGET`` sets the counts from one budget (:func:`~depthnerf.render.source_guide.guided_config`).
    """

    enabled: bool = False
    """Use depth-guided sampling; then ``render_rays`` requires a ``DepthGuide``. Training refuses it (an
    inference-time renderer: ``depthnerf eval/reconstruct --guided``)."""
    n_uniform: int = 8
    """Pass-1 stratified samples over [near, far] on occupied rays (catch what the guess misses)."""
    n_window: int = 16
    """Pass-1 stratified samples inside the guide's window on occupied rays."""
    n_importance: int = 16
    """Pass-2 inverse-CDF samples on occupied rays."""
    n_gaussian: int = 8
    """Pass-2 samples from a Gaussian at the pass-1 depth on occupied rays."""
    n_empty: int = 16
    """Pass-1 stratified samples over [near, far] on rays the source view sees as empty."""
    n_empty_importance: int = 8
    """Pass-2 inverse-CDF samples on rays the source view sees as empty."""
    gaussian_std: float = 0.01
    """Standard deviation of the pass-2 Gaussian samples (ray-distance units)."""
    pdf_epsilon: float = 1e-5
    """Added to the pass-1 bin masses before normalising them into a pdf."""
    first_pass: Literal["fine", "coarse"] = "fine"
    """Network of pass 1. "fine" (default) reuses its evaluations in pass 2; "coarse" re-evaluates the whole
    union with the fine network (costlier, for comparison). Without a fine network both passes use the coarse."""
    align_samples: int = 32
    """Coarse samples per ray of the cheap render of the source view that the prior is aligned against."""
    align_min_opacity: float = 0.5
    """Source pixels at least this opaque in that render anchor the alignment. Soft CPU models rarely exceed
    0.9 (a threshold of 0.9 left the guide empty on most objects)."""
    march_steps: int = 128
    """Points per target ray tested against the source depth map (epipolar march between near and far)."""
    spread: float = 0.1
    """Half-width of the window around a surface guess, and the margin (source z units) within which a point in
    front of the source-visible surface still counts as possibly occupied. Covers prior error and soft density."""
    surface_tolerance: float = 0.03
    """A crossing of the source-visible surface is trusted only if the march points on both sides of it are
    within this distance (source z) of the surface; otherwise the ray entered the source's shadow."""
    mask_dilation: int = 2
    """Widening of the source's z map in pixels (a background pixel within that many pixels of the mask takes the
    smallest foreground z there) so rays grazing the silhouette, where soft density still renders, are not classed
    as empty; the mask itself, where a surface guess is trusted, is not widened."""
    march_chunk: int = 8192
    """Target rays marched at once (bounds memory to about ``march_chunk * march_steps * 60`` bytes)."""

    @property
    def budget(self) -> int:
        """Samples per occupied ray (the four occupied-ray counts together)."""
        return self.n_uniform + self.n_window + self.n_importance + self.n_gaussian


@dataclass
class RenderConfig:
    """Everything ``render_rays`` needs besides the networks and the rays."""

    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    """The paper's coarse-to-fine sampler."""
    guided: GuidedConfig = field(default_factory=GuidedConfig)
    """Depth-guided sampling (off by default; on only at inference, ``--guided``)."""
    white_background: bool = True
    """Composite on white: ``rgb += 1 - opacity`` (SRN renders are on white)."""
    sigma_noise_std: float = 0.0
    """Std of Gaussian noise added to sigma in training only, after the field's ReLU (the sum clamped at 0 again
    when compositing), as pixelNeRF's ``noise_std``; the paper uses 0."""
