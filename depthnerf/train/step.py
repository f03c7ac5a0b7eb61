"""One training step: the loss of a batch of objects and its gradient, with no host synchronisation.

:class:`BatchLoss` encodes the source views of all B objects of a rank's batch in one encoder call and renders
all their target rays in one ``render_rays`` call (one field evaluation per pass over ``B x R x S`` points, no
point chunking), as pixelNeRF batches its objects. Two things keep the result a per-object one, independent of
which objects share the batch (so 2 DDP ranks x 2 objects equal 1 process x 4 objects):

* BatchNorm statistics are per object (``depthnerf.model.norm``);
* each object's sample jitter and density noise come from its own generator (``depthnerf.render.noise``).

The loss is pixelNeRF's: the mean over objects of the coarse + fine colour MSE (plus the optional depth,
background-opacity and foreground-opacity terms, each per object then averaged). :func:`train_step` returns the loss
terms as one device tensor; the loop reads it once per log interval. ``per_object=True`` runs the same module once per
object (gradients accumulated, ``--schedule.step_shape per-object``); same result up to float rounding.
:func:`compiled_fields` (``depthnerf train --compile``) runs the fields' MLPs, forward and backward, through
``torch.compile``, which fuses their element-wise work and casts (fewer kernel launches on a GPU).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from depthnerf.model.pixelnerf import FieldRuntime, PixelNeRF
from depthnerf.render.config import RenderConfig
from depthnerf.render.depth_loss import ssi_depth_loss_per_image
from depthnerf.render.draws import PaperDraws, draw_paper
from depthnerf.render.pipeline import render_rays
from depthnerf.render.rays import RayBundle
from depthnerf.train.batching import ItemKey, TrainBatch, item_seed

TERMS = ("total", "coarse", "fine", "depth", "background", "foreground")
"""Order of the loss terms in :meth:`LossTerms.stacked` (and of the logged ``loss*`` values)."""


@dataclass
class LossTerms:
    """Losses of a batch, each the mean over its objects of the per-object value."""

    total: Tensor
    """What is back-propagated."""
    coarse: Tensor
    """MSE of the coarse colour."""
    fine: Tensor
    """MSE of the fine colour (0 without a fine pass)."""
    depth: Tensor
    """Scale/shift-invariant depth loss (0 when off)."""
    background: Tensor
    """Background-opacity term, coarse + fine: measured whether or not it is weighted into ``total``."""
    foreground: Tensor
    """Foreground-opacity term, coarse + fine: measured whether or not it is weighted into ``total``."""

    def stacked(self) -> Float[Tensor, " 6"]:
        """The terms in :data:`TERMS` order, detached, fp32, on the device."""
        return torch.stack([getattr(self, n).detach().float() for n in TERMS])


def background_opacity_per_object(opacity: Float[Tensor, "B R"], foreground: Bool[Tensor, "B R"]
                                  ) -> Float[Tensor, " B"]:
    """Per object, mean squared opacity over the rays whose target pixel is background (0 when there is none):
    ``sum_r [not fg_r] * opacity_r^2 / max(1, #background rays)``; the loss term is its mean over objects."""
    background = ~foreground
    return (opacity.square() * background).sum(-1) / background.sum(-1).clamp_min(1)


def foreground_opacity_per_object(opacity: Float[Tensor, "B R"], foreground: Bool[Tensor, "B R"]
                                  ) -> Float[Tensor, " B"]:
    """Per object, mean squared transparency over the rays whose target pixel shows the object (0 when there is
    none): ``sum_r [fg_r] * (1 - opacity_r)^2 / max(1, #object rays)``, the mask's half of a silhouette loss (the
    other half is :func:`background_opacity_per_object`); the loss term is its mean over objects."""
    return ((1 - opacity).square() * foreground).sum(-1) / foreground.sum(-1).clamp_min(1)


class BatchLoss(torch.nn.Module):
    """Encode a batch's source views, render its target rays, return the losses (DDP wraps this module)."""

    def __init__(self, model: PixelNeRF, render_cfg: RenderConfig, depth_weight: float,
                 background_weight: float = 0.0, runtime: FieldRuntime | None = None,
                 compile_step: str | None = None, foreground_weight: float = 0.0,
                 depth_min_opacity: float = 0.5) -> None:
        """``background_weight`` / ``foreground_weight``: weights of the background- and foreground-opacity terms
        (0 = measured, not back-propagated). ``depth_min_opacity``: rays fainter than this stay out of the depth
        loss (``ScheduleConfig.depth_loss_min_opacity``). ``runtime``: how the field passes run (e.g. :func:`compiled_fields`;
        None: the MLPs as they are).
        ``compile_step``: a ``torch.compile`` backend (``"inductor"``; ``"aot_eager"`` traces without code
        generation) through which :meth:`losses` runs (:func:`compiled_losses`); None: eagerly."""
        super().__init__()
        self.model = model
        self.render_cfg = render_cfg
        self.depth_weight = depth_weight
        self.depth_min_opacity = depth_min_opacity
        self.background_weight = background_weight
        self.foreground_weight = foreground_weight
        self.runtime = runtime
        cuda = any(p.is_cuda for p in model.parameters())
        self._losses = compiled_losses(self.losses, compile_step, cuda) if compile_step else self.losses

    def forward(self, batch: TrainBatch, near: float, far: float,
                generators: Sequence[torch.Generator]) -> LossTerms:
        """The losses of ``batch``; each object's random draws come from its generator, drawn here, before the
        (possibly compiled) :meth:`losses`."""
        draws = draw_paper(tuple(batch.ray_origins.shape[:2]), self.render_cfg, fine=True, sigma_noise=True,
                           generator=list(generators), dtype=batch.ray_origins.dtype,
                           device=batch.ray_origins.device)
        return self._losses(batch, near, far, draws)

    def losses(self, batch: TrainBatch, near: float, far: float, draws: PaperDraws) -> LossTerms:
        """The losses of ``batch`` given the render's random draws (no generator: one traceable function)."""
        enc = self.model.encode(batch.source)
        fine_fn = self.model.field(enc, "fine", self.runtime)  # the coarse MLP when there is no separate fine one
        rays = RayBundle(batch.ray_origins, batch.ray_dirs, torch.full_like(batch.ray_origins[..., 0], near),
                         torch.full_like(batch.ray_origins[..., 0], far))
        out = render_rays(self.model.field(enc, "coarse", self.runtime), fine_fn, rays, self.render_cfg, train=True,
                          draws=draws)
        coarse = torch.mean((out.coarse.rgb - batch.target_rgb) ** 2)  # equal rays per object: mean of means
        fine = torch.mean((out.fine.rgb - batch.target_rgb) ** 2)
        total = coarse + fine
        depth = total * 0
        if self.depth_weight > 0 and batch.target_prior is not None:
            per_object, _ = ssi_depth_loss_per_image(out.fine.normalized_distance(), batch.target_prior,
                                                     batch.target_fg, dirs_cam_z=batch.target_cos,
                                                     opacity=out.fine.opacity, min_opacity=self.depth_min_opacity)
            depth = per_object.mean()
            total = total + self.depth_weight * depth
        # the mask terms: always measured (logged as loss_background, the floater diagnostic, and loss_foreground),
        # back-propagated only when weighted
        terms = []
        for per_object, weight in ((background_opacity_per_object, self.background_weight),
                                   (foreground_opacity_per_object, self.foreground_weight)):
            term = (per_object(out.coarse.opacity, batch.target_fg) + per_object(out.fine.opacity, batch.target_fg)
                    ).mean()
            if weight > 0:
                total = total + weight * term
            terms.append(term if weight > 0 else term.detach())
        background, foreground = terms
        return LossTerms(total=total, coarse=coarse, fine=fine, depth=depth, background=background,
                         foreground=foreground)


def compiled_fields(model: PixelNeRF) -> FieldRuntime:
    """A runtime whose coarse and fine passes call ``torch.compile`` wrappers of the model's MLP forwards (one
    wrapper per module, shared when fine reuses coarse; the modules are not changed). Training shapes are static
    within a schedule phase, so each wrapper compiles once per phase and pass. Same values as the eager MLPs up
    to float rounding (fused element-wise kernels may round differently)."""
    compiled = {id(mlp): torch.compile(mlp.forward) for mlp in (model.coarse, model.fine) if mlp is not None}
    return FieldRuntime(forwards={which: compiled[id(model.network(which))] for which in ("coarse", "fine")})


def compiled_losses(losses: Callable[..., LossTerms], backend: str, cuda: bool) -> Callable[..., LossTerms]:
    """``torch.compile`` of :meth:`BatchLoss.losses` with ``backend``: encoder, both render passes and the loss
    terms, forward and backward, as one graph (its random draws are inputs, so no generator breaks it). With
    ``cuda`` and inductor, mode ``reduce-overhead``: the step's kernels are replayed as CUDA graphs instead of
    launched one by one from Python. Training shapes are static within a schedule phase, so it compiles once per
    phase. Same values as the eager step up to float rounding (fused kernels may round differently)."""
    mode = "reduce-overhead" if cuda and backend == "inductor" else None
    compiled = torch.compile(losses, backend=backend, mode=mode)

    def step(batch: TrainBatch, near: float, far: float, draws: PaperDraws) -> LossTerms:
        torch.compiler.cudagraph_mark_step_begin()  # a new training step: earlier outputs may be overwritten
        return compiled(batch, near, far, draws)
    return step


def object_generators(keys: Sequence[ItemKey], step: int, device: torch.device) -> list[torch.Generator]:
    """Each object's renderer generator at ``step`` (a function of the item key alone)."""
    return [torch.Generator(device).manual_seed(item_seed(key.seed, step, 1)) for key in keys]


def train_step(runner: torch.nn.Module, batch: TrainBatch, keys: Sequence[ItemKey], step: int, near: float,
               far: float, device: torch.device, *, amp: contextlib.AbstractContextManager | None = None,
               per_object: bool = False, distributed: bool = False) -> Float[Tensor, " 6"]:
    """Forward and backward of one step (gradients accumulate in the parameters; the caller zeroes them and
    steps the optimiser). Returns the :data:`TERMS` on the device: no host synchronisation here."""
    amp = amp if amp is not None else contextlib.nullcontext()
    gens = object_generators(keys, step, device)
    if not per_object:
        with amp:
            terms = runner(batch, near, far, gens)
        terms.total.backward()
        return terms.stacked()
    sums = torch.zeros(len(TERMS), device=device)
    for k in range(len(keys)):
        last = k == len(keys) - 1
        sync = runner.no_sync() if distributed and not last else contextlib.nullcontext()
        with sync:
            with amp:
                terms = runner(batch.item(k), near, far, gens[k:k + 1])
            (terms.total / len(keys)).backward()
        sums += terms.stacked()
    return sums / len(keys)
