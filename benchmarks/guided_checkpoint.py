"""Checkpoint mode of ``bench_guided_sampling.py``: a trained pixelNeRF, its own sampler vs depth-guided sampling.

For the first ``--objects`` objects of a split, each object is prepared exactly as ``depthnerf eval`` prepares it
(:func:`depthnerf.eval.objects.prepare_object`: input view 64 encoded once with the checkpoint's depth prior from
the prior cache, targets = the other views with ``--views-stride``, all at the training resolution). The same
target views are then rendered one at a time

- with the checkpoint's own sampler (``render`` of its training config, e.g. 32 + 16 + 8) or, with
  ``--reference-samples 64,16,16``, the paper's sampler on the same network: the reference row;
- with depth-guided sampling (:mod:`depthnerf.render.source_guide`) at each ``--budgets`` total of samples per
  occupied ray (:func:`guided_config` splits it), the guide built from the input view's prior aligned to metric depth
  against a cheap coarse render of the input view (:func:`source_depth`; without a prior, that render's depth).
  The rows report which fraction of target rays the guide covered (a trusted surface guess / any window); rays
  it does not cover are sampled as empty space, with half the budget;
- with ``--plain-samplers "C,I,G ..."``: the reference sampler with fewer samples and no guide (the ablation that
  shows whether the guide, or merely fewer samples, buys the speed).

Per setting: wall-clock ms per view (fastest of ``--repeats``, torch threads as the environment sets them; guided
rows include building the guide per view and the alignment render once per object, amortised over that object's
rendered views), nominal samples and measured network evaluations per ray, PSNR/SSIM against ground truth with
:mod:`depthnerf.eval.metrics` (mean over views per object, then over objects, as the protocol), the PSNR change
against the reference, the PSNR of the guided render against the reference render, and the speed-up. A setting
meets issue 4's target when it is >= 3x faster than the reference at <= 0.1 dB PSNR loss.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from depthnerf.data.protocol import protocol_views
from depthnerf.data.srn import index_split
from depthnerf.errors import DepthnerfError
from depthnerf.eval.metrics import object_metrics, psnr
from depthnerf.eval.objects import PreparedObject, prepare_object
from depthnerf.files import write_text_atomic
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.pretrained.load import load_pretrained
from depthnerf.render.config import GuidedConfig, RenderConfig
from depthnerf.render.pipeline import FieldFn
from depthnerf.render.source_guide import SourceGuide, guided_config, guided_record, source_depth
from depthnerf.render.views import render_views, view_rays

__all__ = ["guided_config", "source_depth", "run_checkpoint", "reference_render"]

TARGET_SPEEDUP = 3.0
"""Issue 4: guided sampling must be at least this much faster than the reference sampler ..."""
TARGET_MAX_LOSS_DB = 0.1
"""... while losing at most this much PSNR."""
class CountedField:
    """A field wrapper counting the points it evaluates (network evaluations)."""

    def __init__(self, fn: FieldFn):
        self.fn, self.points = fn, 0

    def __call__(self, pts: Tensor, dirs: Tensor) -> tuple[Tensor, Tensor]:
        self.points += pts.shape[:-1].numel()
        return self.fn(pts, dirs)


def timed(fn: Callable, repeats: int):
    """``fn()``'s result and its fastest wall time in seconds over ``repeats`` calls (the CPU may be shared)."""
    best, out = float("inf"), None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


@dataclass
class Setting:
    """One row of the table: a renderer configuration and what was measured with it."""

    name: str
    """``reference`` or ``guided-<budget>``."""
    render: RenderConfig
    """The renderer configuration."""
    samples: str
    """Nominal samples per ray (guided: occupied / empty rays)."""
    seconds: float = 0.0
    """Summed wall time of all rendered views (guided: plus the alignment renders)."""
    views: int = 0
    """Rendered views."""
    points: int = 0
    """Network evaluations."""
    rays: int = 0
    """Rendered rays."""
    objects: list[dict] = field(default_factory=list)
    """Per object: ``object_id``, ``psnr``, ``ssim``, ``psnr_vs_reference`` (None on the reference row)."""
    guide_valid: int = 0
    """Guided rows: target rays with a trusted surface guess (``DepthGuide.valid``)."""
    guide_occupied: int = 0
    """Guided rows: target rays the guide gives a window (``DepthGuide.occupied``); the others are empty."""

    @property
    def guided(self) -> bool:
        return self.render.guided.enabled


def reference_render(render: RenderConfig, samples: str | None) -> RenderConfig:
    """The reference renderer: ``render`` with its sampler's (coarse, importance, Gaussian) counts replaced by
    ``samples`` ("C,I,G", e.g. the paper's "64,16,16"); ``render`` itself when ``samples`` is None."""
    if samples is None:
        return render
    try:
        c, i, g = (int(n) for n in samples.split(","))
    except ValueError:
        raise DepthnerfError(f"sampler counts must be three integers C,I,G (e.g. 64,16,16), got {samples!r}") from None
    if c < 1 or i < 0 or g < 0:
        raise DepthnerfError(f"sampler counts need C >= 1 and I, G >= 0, got {samples!r}")
    return dataclasses.replace(render, sampler=dataclasses.replace(render.sampler, n_coarse=c, n_importance=i,
                                                                   n_gaussian=g))


def bench_guided(args: argparse.Namespace, base: GuidedConfig | None = None) -> GuidedConfig:
    """The guided settings of the command line (``--align-samples``, ``--align-min-opacity``, ``--spread``) on
    ``base`` (the checkpoint's ``render.guided``); the budget's counts are set per row."""
    return dataclasses.replace(base or GuidedConfig(), align_samples=args.align_samples,
                               align_min_opacity=args.align_min_opacity, spread=args.spread)


def _settings(render: RenderConfig, budgets: list[int], reference: RenderConfig, guided: GuidedConfig,
              plain: list[str] = ()) -> list[Setting]:
    sc = reference.sampler
    rows = [Setting("reference", reference, f"{sc.n_coarse}+{sc.n_importance}+{sc.n_gaussian}")]
    for counts in plain:  # the paper's sampler with fewer samples, no guide: is the guide what buys the speed?
        cfg = reference_render(render, counts)
        s = cfg.sampler
        name = f"{s.n_coarse}+{s.n_importance}+{s.n_gaussian}"
        rows.append(Setting(f"plain-{name}", cfg, name))
    for b in budgets:
        g = guided_config(b, guided.align_samples, guided)
        rows.append(Setting(f"guided-{b}", dataclasses.replace(render, guided=g),
                            f"{g.n_uniform}+{g.n_window}+{g.n_importance}+{g.n_gaussian} / "
                            f"{g.n_empty}+{g.n_empty_importance}"))
    return rows


def _bench_object(obj: PreparedObject, fields: tuple[CountedField, CountedField], settings: list[Setting],
                  near: float, far: float, args: argparse.Namespace) -> float:
    """Render the object's targets with every setting, accumulate into ``settings``; returns the alignment s."""
    coarse, fine = fields
    src, tgt = obj.source, obj.targets
    src_mask = src.masks[:1]
    guided = bench_guided(args, settings[0].render.guided)
    depth, t_align = timed(lambda: source_depth(coarse, src.poses[:1], src.intrinsics, near, far, obj.encoded.disparity,
                                                src_mask, settings[0].render, guided, args.chunk), 1)
    source_guide = SourceGuide(c2w=src.poses[:1], intr=src.intrinsics, depth=depth, mask=src_mask, guided=guided)
    gts = tgt.images.permute(0, 2, 3, 1).numpy()
    ref_preds = None
    for s in settings:
        preds = []
        for pose in tgt.poses:
            c2w = pose[None]

            def render(c2w=c2w, s=s):
                guide = None
                if s.guided:
                    rays = view_rays(c2w, tgt.intrinsics, near, far)
                    guide = source_guide.guide(rays)
                return render_views(coarse, fine, c2w, tgt.intrinsics, near, far, s.render, chunk=args.chunk,
                                    guide=guide).rgb[0], guide

            p0 = coarse.points + fine.points
            (rgb, guide), seconds = timed(render, args.repeats)
            if guide is not None:
                s.guide_valid += int(guide.valid.sum())
                s.guide_occupied += int(guide.occupied.sum())
            s.points += (coarse.points + fine.points - p0) // max(1, args.repeats)
            s.seconds += seconds
            s.rays += tgt.intrinsics.height * tgt.intrinsics.width
            s.views += 1
            preds.append(rgb.float().cpu().numpy())
        if s.guided:
            s.seconds += t_align
        preds = np.stack(preds)
        ref_preds = preds if ref_preds is None else ref_preds
        m = object_metrics(obj.targets.record.object_id, preds, gts)
        vs_ref = None if preds is ref_preds else float(np.mean([psnr(p, r) for p, r in zip(preds, ref_preds,
                                                                                          strict=True)]))
        s.objects.append({"object_id": m.object_id, "psnr": m.psnr, "ssim": m.ssim, "psnr_vs_reference": vs_ref})
    return t_align


def _rows(settings: list[Setting]) -> list[dict]:
    ref_ms = 1000 * settings[0].seconds / settings[0].views
    ref_psnr = float(np.mean([o["psnr"] for o in settings[0].objects]))
    rows = []
    for s in settings:
        ms = 1000 * s.seconds / s.views
        mean = {k: None if s is settings[0] and k == "psnr_vs_reference" else float(np.mean([o[k] for o in s.objects]))
                for k in ("psnr", "ssim", "psnr_vs_reference")}
        speedup = ref_ms / ms
        rows.append({"name": s.name, "guided": s.guided, "samples_per_ray": s.samples,
                     "evals_per_ray": s.points / s.rays, "ms_per_view": ms,
                     "guide_valid_fraction": s.guide_valid / s.rays if s.guided else None,
                     "guide_occupied_fraction": s.guide_occupied / s.rays if s.guided else None,
                     "speedup": speedup, **mean,
                     "psnr_delta": mean["psnr"] - ref_psnr,
                     "meets_target": s.guided and speedup >= TARGET_SPEEDUP
                     and ref_psnr - mean["psnr"] <= TARGET_MAX_LOSS_DB,
                     "views": s.views, "per_object": s.objects})
    return rows


def run_checkpoint(args: argparse.Namespace) -> dict:
    """Run the checkpoint benchmark (arguments of ``bench_guided_sampling.py``); print and return the table."""
    pre = load_pretrained(args.checkpoint)
    cfg = pre.spec
    if cfg.render.guided.enabled:
        raise DepthnerfError(f"{pre.path}: the checkpoint's renderer is already depth-guided; the reference must be "
                             "the paper's sampler")
    if args.objects < 1 or args.views_stride < 1:
        raise DepthnerfError(f"--objects and --views-stride must be >= 1 (got {args.objects}, {args.views_stride})")
    budgets = [int(b) for b in str(args.budgets).split(",") if b.strip()]
    data = Path(args.data)
    category = args.category or cfg.category
    records = index_split(data, category, args.split, check_files=False).objects[: args.objects]
    session = InferenceSession(pre, SessionOptions(inputs="dataset", data_root=data, records=records))
    near, far = cfg.z_range
    res = cfg.resolution
    plain = [c for c in str(args.plain_samplers or "").split() if c]
    settings = _settings(cfg.render, budgets, reference_render(cfg.render, args.reference_samples),
                         bench_guided(args, cfg.render.guided), plain)
    align = []
    for k, record in enumerate(records):
        obj = prepare_object(session, record, protocol_views(record.num_views, args.views_stride))
        enc = obj.encoded.enc
        fields = CountedField(pre.model.field(enc, "coarse")), CountedField(pre.model.field(enc, "fine"))
        if k == 0:  # warm-up (allocator, thread pools), not timed
            render_views(*fields, obj.targets.poses[:1], obj.targets.intrinsics, near, far, cfg.render,
                         chunk=args.chunk)
        align.append(_bench_object(obj, fields, settings, near, far, args))
    rows = _rows(settings)
    meets = [r["name"] for r in rows if r["meets_target"]]
    result = {
        "checkpoint": str(pre.path.resolve()), "checkpoint_sha256": pre.sha256, "checkpoint_step": pre.step,
        "preset": cfg.preset, "depth_prior": cfg.prior.estimator,
        "guide_depth": "prior aligned to a coarse render" if cfg.depth_aware else "coarse render (no prior)",
        "data": str(data.resolve()), "category": category, "split": args.split,
        "objects": [r.object_id for r in records], "views_per_object": settings[0].views // len(records),
        "views_stride": args.views_stride, "resolution": res, "z_range": [near, far],
        "reference_sampler": settings[0].samples, "torch_threads": torch.get_num_threads(), "repeats": args.repeats, "align_samples": args.align_samples,
        "align_min_opacity": args.align_min_opacity,
        "align_ms_per_object": 1000 * float(np.mean(align)), "guide": guided_record(bench_guided(args, cfg.render.guided))["guide"],
        "target": {"speedup": TARGET_SPEEDUP, "max_psnr_loss_db": TARGET_MAX_LOSS_DB},
        "rows": rows, "meets_target": meets,
    }
    print_table(result)
    if args.json:
        write_text_atomic(Path(args.json), json.dumps(result, indent=1) + "\n")
    return result


def print_table(result: dict) -> None:
    """The Markdown table of :func:`run_checkpoint` and the target verdict."""
    print(f"{result['checkpoint']} (step {result['checkpoint_step']}, prior {result['depth_prior']}): "
          f"{len(result['objects'])} {result['category']}_{result['split']} objects x "
          f"{result['views_per_object']} views at {result['resolution']}px, {result['torch_threads']} torch "
          f"threads; guide depth: {result['guide_depth']} (alignment {result['align_ms_per_object']:.0f} ms per "
          "object, included in the guided rows)")
    print("| setting | samples/ray | evals/ray | guided rays (surface / window) | ms/view | speed-up | PSNR | SSIM | "
          "dPSNR vs ref | PSNR vs ref render | meets |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in result["rows"]:
        cover = "-" if r["guide_valid_fraction"] is None else \
            f"{r['guide_valid_fraction']:.0%} / {r['guide_occupied_fraction']:.0%}"
        print(f"| {r['name']} | {r['samples_per_ray']} | {r['evals_per_ray']:.1f} | {cover} | {r['ms_per_view']:.1f} | "
              f"{r['speedup']:.2f}x | {r['psnr']:.3f} | {r['ssim']:.4f} | {r['psnr_delta']:+.3f} | "
              f"{'-' if r['psnr_vs_reference'] is None else format(r['psnr_vs_reference'], '.2f')} | "
              f"{'yes' if r['meets_target'] else 'no'} |")
    verdict = ", ".join(result["meets_target"]) or "none"
    print(f">= {TARGET_SPEEDUP:g}x faster at <= {TARGET_MAX_LOSS_DB:g} dB PSNR loss: {verdict}")
