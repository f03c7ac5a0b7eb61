"""``depthnerf eval``: evaluate a run or checkpoint by the SRN protocol (see :mod:`depthnerf.eval.protocol`).

``depthnerf eval (--run RUN_DIR | --checkpoint PATH_OR_NAME) [--data DIR] [--split test] [--out OUT_DIR]
[--views-stride K] [--input-views V [V ...]] [--max-objects N] [--resolution R] [--no-mesh] [--mesh-resolution M]
[--mesh-threshold auto|silhouette|local|X] [--save-renders] [--ssim uniform7|gaussian11|gaussian11-zeropad] [--scored png8|float] [--objects pixelnerf|all]
[--overwrite] [--strict]``

Writes ``OUT_DIR/summary.json`` and ``OUT_DIR/per_object.csv`` (default ``OUT_DIR``: ``RUN_DIR/eval/<split>`` with
``--run``, required with ``--checkpoint``; never the dataset root or one of its split folders), so ``depthnerf
compare RUN_DIR`` finds the summary. ``--data`` defaults to the dataset the run was trained on. Targets are scored
at the training resolution unless ``--resolution`` says otherwise (``--resolution 128`` = the paper's protocol); the
input view is always encoded at the training resolution, with the run's depth prior (its cache must exist for the
split: ``depthnerf depth ... --splits test --resolution <training resolution>``). Every file of the split is checked
before anything is scored (as ``train`` does), so a corrupt image in a view that is not scored is still an error;
``--strict`` makes problems in the optional parts (depth, masks, meshes) errors too (see docs/data.md).

``--ssim``, ``--scored`` and ``--objects`` select the protocol choices that move published numbers (defaults:
pixelNeRF's; :mod:`depthnerf.eval.config`). Every object's result is kept under ``OUT_DIR/objects/``: the same
command run again continues a killed evaluation, other settings there (or data changed since, a fingerprint of
its files: :mod:`depthnerf.data.fingerprint`) are refused unless ``--overwrite``.
``torchrun --nproc_per_node=N -m depthnerf eval ...`` shares the objects out over N processes (one GPU each,
``LOCAL_RANK`` picks it; gloo on CPU) and rank 0 writes the merged outputs (:mod:`depthnerf.eval.shards`).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable
from datetime import timedelta
from pathlib import Path

from depthnerf.depth.estimators import ESTIMATORS
from depthnerf.errors import DepthnerfError
from depthnerf.model.config import ENCODER_NORMS
from depthnerf.render.config import COMPILE_MODES, DEFAULT_BUDGET, GATHERS, GuidedConfig

COLLECTIVE_TIMEOUT = timedelta(hours=6)
"""How long rank 0 waits for the slowest rank's share of the objects before the merge (multi-process runs)."""


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--run", type=Path, help="run folder (uses checkpoints/best, else the latest checkpoint)")
    src.add_argument("--checkpoint", help="weights file, checkpoint folder, shipped name (depthnerf checkpoints) or "
                     "Hub file hf://OWNER/REPO[/FILE][@REVISION]")
    p.add_argument("--data", type=Path, help="dataset root (default: the run's training data root)")
    p.add_argument("--category", help="category folder prefix (default: the run's)")
    p.add_argument("--split", default="test", choices=["train", "val", "test"], help="split (default test)")
    p.add_argument("--out", type=Path, help="output folder (default RUN_DIR/eval/<split> with --run); not the "
                                             "dataset or one of its split folders")
    p.add_argument("--views-stride", type=int, default=1, help="score every K-th target view (default 1: all)")
    p.add_argument("--input-views", type=int, nargs="+", metavar="VIEW",
                   help="views each object is conditioned on, the first the primary one (default: 64, the SRN "
                        "protocol; 64 104: pixelNeRF's two-view protocol); every other view is a target")
    p.add_argument("--max-objects", type=int, help="only the first N objects (sorted by id)")
    p.add_argument("--resolution", type=int,
                   help="render/score resolution (default: the checkpoint's training resolution; 128 = paper)")
    p.add_argument("--chunk", type=int,
                   help="rays per render pass (bounds memory; default 4096 on CPU, 65536 on CUDA)")
    p.add_argument("--no-mesh", action="store_true", help="skip mesh extraction and Chamfer/F-score")
    p.add_argument("--mesh-resolution", type=int, default=None, help="marching-cubes grid samples (default 128)")
    p.add_argument("--mesh-threshold", default=None,
                   help="marching-cubes density level: a number, auto (default: half the median peak density "
                        "along the opaque input rays), silhouette (the level whose input-view outline best matches "
                        "the input's mask: keeps thin parts, a thicker surface) or local (half the peak along each "
                        "input ray, between the two)")
    p.add_argument("--fscore-tau", type=float, default=None, help="F-score threshold in GT diagonals (0.01)")
    p.add_argument("--mesh-points", type=int, default=None, help="surface samples per mesh (default 100000)")
    p.add_argument("--save-renders", action="store_true", help="write renders, meshes and renders.csv")
    p.add_argument("--ssim", choices=("uniform7", "gaussian11", "gaussian11-zeropad"), default="uniform7",
                   help="SSIM: uniform7 (default, pixelNeRF: 7x7 uniform window), gaussian11 (11x11 "
                        "Gaussian sigma 1.5, Wang et al./scikit-image), gaussian11-zeropad (the same, zero-padded: "
                        "the 3DGS ssim() Splatter Image uses)")
    p.add_argument("--scored", choices=("png8", "float"), default=None,
                   help="score the renders as 8-bit PNGs, truncated (default, pixelNeRF's paper numbers, "
                        "calc_metrics.py) or as floats (the numbers pixelNeRF's eval.py prints)")
    p.add_argument("--quantize", action="store_true", help="same as --scored png8 (the default)")
    p.add_argument("--objects", choices=("pixelnerf", "all"), default="pixelnerf",
                   help="pixelnerf (default): leave out the objects pixelNeRF's evaluation cannot load (SRN's "
                        "all-white test car 876d92ce6a0e4bf399588eee976baae); all: score every object")
    p.add_argument("--overwrite", action="store_true",
                   help="start over in OUT_DIR, discarding the objects an earlier evaluation finished there")
    p.add_argument("--method", help="row label for depthnerf compare (default from the depth prior)")
    p.add_argument("--depth", choices=ESTIMATORS,
                   help="override the depth prior recorded in the checkpoint (its cache must exist)")
    p.add_argument("--depth-checkpoint", help="override the depth estimator weights recorded in the checkpoint")
    add_guided_flags(p)
    add_samples_flag(p)
    p.add_argument("--lpips-trunk", type=Path, help="local torchvision VGG16 weights for LPIPS (never downloaded)")
    p.add_argument("--pixel-center", type=float,
                   help="read the data with pixel (i, j) at (j + C, i + C) instead of the checkpoint's trained "
                        "data.pixel_center (measures what a convention mismatch costs)")
    p.add_argument("--encoder-norm", choices=ENCODER_NORMS, default="running",
                   help="encoder BatchNorm statistics: running (pixelNeRF, default) or the input image's own, as "
                        "training normalises each object")
    p.add_argument("--no-symmetry", action="store_true",
                   help="mirror models: condition on no symmetry plane (the model's no-plane mode)")
    p.add_argument("--symmetry-plane", type=float, nargs=4, metavar=("NX", "NY", "NZ", "D"),
                   help="mirror models: the objects' symmetry plane n.x = d in the world frame (default: the "
                        "dataset card's, else ShapeNet's x = 0)")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu, cuda or cuda:N")
    add_precision_flags(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--strict", action="store_true",
                   help="a problem in an optional part of the data (depth/, mask/, mesh.ply) is an error")


def add_precision_flags(p: argparse.ArgumentParser) -> None:
    """How the fields render on the device (``eval`` and ``reconstruct``; depthnerf.render.precision)."""
    p.add_argument("--fp32", action="store_true", help="render in fp32 on CUDA too (default there: bf16 autocast)")
    p.add_argument("--compile", action="store_true",
                   help="torch.compile the field MLPs (opt-in; compile time is paid once per process)")
    p.add_argument("--compile-mode", choices=COMPILE_MODES, metavar="MODE",
                   help="torch.compile mode for --compile (implies it): " + ", ".join(COMPILE_MODES)
                        + "; max-autotune* fuse the element-wise work into Triton matrix products on CUDA "
                          "(compiles for minutes first)")
    p.add_argument("--bf16-residual", action="store_true",
                   help="CUDA: keep the field MLPs' residual stream in bf16 under bf16 autocast (half its memory "
                        "traffic; renders differ by bf16 rounding; opt-in)")
    p.add_argument("--gather", choices=GATHERS, default="before",
                   help="where the fields gather their pixel-aligned features: before (default) the MLP call, "
                        "inside the MLP forward, so inside the compiled graph (implies --compile), inside-bf16 the "
                        "same from bf16 maps (opt-in; renders differ by float rounding)")


def add_guided_flags(p: argparse.ArgumentParser, budget: Callable[[str], int] = int) -> None:
    """``--guided [BUDGET]`` (read by ``budget``) and ``--guided-align-samples`` (``eval`` and ``reconstruct``;
    :func:`guided_request`)."""
    p.add_argument("--guided", type=budget, nargs="?", const=DEFAULT_BUDGET, metavar="BUDGET",
                   help="render with depth-guided sampling, BUDGET samples per occupied ray "
                        f"(default {DEFAULT_BUDGET})")
    p.add_argument("--guided-align-samples", type=int, default=None,
                   help="coarse samples of the source render the prior is aligned to for --guided "
                        f"(default {GuidedConfig.align_samples})")


def add_samples_flag(p: argparse.ArgumentParser) -> None:
    """``--samples COARSE IMPORTANCE GAUSSIAN`` (``eval`` and ``reconstruct``; :attr:`SessionOptions.samples
    <depthnerf.infer.session.SessionOptions.samples>`, checked by :func:`~depthnerf.infer.session.check_samples`)."""
    p.add_argument("--samples", type=int, nargs=3, metavar=("COARSE", "IMPORTANCE", "GAUSSIAN"),
                   help="samples per ray of the checkpoint's sampler instead of its trained counts (the CPU "
                   "presets': 32 16 8; 16 8 4 renders about twice as fast)")


def guided_request(budget: int | None, align_samples: int | None):
    """The ``--guided [BUDGET]`` / ``--guided-align-samples`` flags: None (the checkpoint's sampler) or the guided
    config of that budget (:func:`depthnerf.render.source_guide.guided_config`; ``align_samples`` None: the
    default count); a count below 1 is refused, and so is a count without ``--guided`` (it would set nothing)."""
    from depthnerf.render.source_guide import guided_config

    if align_samples is not None and align_samples < 1:
        raise DepthnerfError(f"--guided-align-samples must be >= 1, got {align_samples}")
    if budget is None:
        if align_samples is not None:
            raise DepthnerfError(f"--guided-align-samples {align_samples} applies only with --guided")
        return None
    return guided_config(budget, GuidedConfig.align_samples if align_samples is None else align_samples)


MESH_FLAG_DEFAULTS: dict[str, object] = {"mesh_resolution": 128, "mesh_threshold": "auto", "fscore_tau": 0.01,
                                         "mesh_points": 100_000}
"""The geometry flags of ``eval`` (argparse ``dest``) and their defaults, filled in by :func:`check_flags` (the
parser leaves them None, so that one given with ``--no-mesh`` is refused instead of ignored)."""


def check_flags(args: argparse.Namespace) -> None:
    """One line naming the flag when ``--pixel-center``, ``--mesh-points``, ``--fscore-tau``,
    ``--symmetry-plane`` (or it with ``--no-symmetry``) or ``--lpips-trunk`` (a file that is not there) cannot work,
    or a geometry flag comes with ``--no-mesh`` (checked before anything loads); then fills in the geometry flags
    not given (:data:`MESH_FLAG_DEFAULTS`)."""
    from depthnerf.data.symmetry import normalized_plane

    given = [dest for dest in MESH_FLAG_DEFAULTS if getattr(args, dest) is not None]
    if args.no_mesh and given:  # else the flag was silently ignored
        flags = " ".join("--" + dest.replace("_", "-") for dest in given)
        raise DepthnerfError(f"{flags} {'sets' if len(given) == 1 else 'set'} the mesh, which --no-mesh skips: "
                             "pass one or the other")
    for dest, default in MESH_FLAG_DEFAULTS.items():
        if getattr(args, dest) is None:
            setattr(args, dest, default)
    if args.pixel_center is not None and not 0 <= args.pixel_center < 1:  # NaN fails too
        raise DepthnerfError(f"--pixel-center must be in [0, 1) (a principal-point shift of a fraction of a pixel: "
                             f"0.0 = pixelNeRF's reading, 0.5 = Blender's), got {args.pixel_center}")
    if args.mesh_points < 1:
        raise DepthnerfError(f"--mesh-points must be >= 1, got {args.mesh_points}")
    if not 0 < args.fscore_tau < math.inf:  # NaN fails too; at inf every point is within it (F-score 1)
        raise DepthnerfError(f"--fscore-tau must be > 0 and finite (a distance in GT diagonals), got "
                             f"{args.fscore_tau}")
    if args.symmetry_plane is not None:
        normalized_plane(args.symmetry_plane, "--symmetry-plane")
        if args.no_symmetry:  # else the plane was silently dropped
            raise DepthnerfError("--symmetry-plane and --no-symmetry contradict each other: pass one of them")
    if args.lpips_trunk is not None and not args.lpips_trunk.is_file():  # else LPIPS were silently "unavailable"
        raise DepthnerfError(f"--lpips-trunk {args.lpips_trunk}: no such file (torchvision VGG16 weights, "
                             "e.g. vgg16-397923af.pth)")


def symmetry_note(args: argparse.Namespace, mirror: bool, checkpoint: str) -> str | None:
    """The ``note:`` line for ``--symmetry-plane`` / ``--no-symmetry`` on a model without the mirror branch (they
    change nothing there), else None."""
    flags = [f for f, given in (("--symmetry-plane", args.symmetry_plane is not None),
                                ("--no-symmetry", args.no_symmetry)) if given]
    if mirror or not flags:
        return None
    return (f"note: {' and '.join(flags)} {'have' if len(flags) > 1 else 'has'} no effect: {checkpoint} has no "
            "mirror-symmetric conditioning (it was not trained with --model.mirror true)")


def _choices(args: argparse.Namespace):
    from depthnerf.eval.config import ProtocolChoices

    if args.quantize and args.scored == "float":
        raise DepthnerfError("--quantize (= --scored png8) contradicts --scored float: pass one of them")
    return ProtocolChoices(ssim=args.ssim, scored=args.scored or "png8", objects=args.objects).check()


def _process(device: str):
    """This process's place in the job: a torchrun rank (its process group set up, one GPU each by
    ``LOCAL_RANK``, gloo on CPU; a device refusal printed once, :func:`depthnerf.distributed.setup`) or the only
    process."""
    from depthnerf.distributed import DistInfo, pick_device, setup

    if int(os.environ.get("WORLD_SIZE", "1")) > 1:
        return setup(device, timeout=COLLECTIVE_TIMEOUT)
    return DistInfo(rank=0, world=1, device=pick_device(device))


def check_category(data: Path, category: str | None, split: str, trained: str, checkpoint: str,
                   warn: bool = True) -> None:
    """A warning line (where ``warn``: rank 0 of a torchrun job) when ``--category`` scores a model on another
    category than it was trained on; an error naming the categories the data holds when it has none of the
    model's (instead of a missing split folder)."""
    from depthnerf.data.srn import discover_categories, split_dir

    if category is not None:
        if category != trained and warn:
            print(f"warning: scoring {checkpoint}, a {trained} model, on {category} data (--category {category}); "
                  "the figures measure a category it was not trained on", file=sys.stderr, flush=True)
        return
    if split_dir(data, trained, split).is_dir():
        return
    held = [c for c in discover_categories(data) if split_dir(data, c, split).is_dir()]
    if held:
        raise DepthnerfError(f"{data}: holds {', '.join(f'{c}_{split}' for c in held)} but no {trained}_{split}, "
                             f"and {checkpoint} is a {trained} model; pass a {trained} dataset, or --category "
                             f"{held[0]} to score it on {held[0]} anyway")


def empty_meshes_text(summary: dict) -> str:
    """`` (N of M meshes empty)`` after the geometry figures when predicted meshes were empty (their Chamfer-L1 and
    F-score are worst-case values, not measured), else ``""``."""
    empty = summary.get("empty_predictions") or 0
    return f" ({empty} of {summary.get('geometry_objects', '?')} meshes empty)" if empty else ""


def _request(args: argparse.Namespace):
    """The output folder, protocol config and guided setup the flags ask for, from the command line alone (every
    flag checked before the checkpoint and the data load): ``(out, cfg, guided)``."""
    from depthnerf.eval.geometry_metrics import GeometryConfig
    from depthnerf.eval.metrics import LpipsConfig
    from depthnerf.eval.protocol import ProtocolConfig
    from depthnerf.infer.session import check_samples
    from depthnerf.render.mesh_level import parse_level

    check_flags(args)
    if args.run is not None and not args.run.is_dir():  # else "its parent is a file" about the default --out
        raise DepthnerfError(f"{args.run}: --run needs a training run folder, "
                             f"{'this is a file' if args.run.exists() else 'no such folder'}")
    choices = _choices(args)
    out = args.out
    if out is None:
        if args.run is None:
            raise DepthnerfError("--out OUT_DIR is required with --checkpoint")
        out = args.run / "eval" / args.split
    guided = guided_request(args.guided, args.guided_align_samples)
    check_samples(args.samples)
    cfg = ProtocolConfig(
        split=args.split, category=args.category, views_stride=args.views_stride, max_objects=args.max_objects,
        input_views=None if args.input_views is None else tuple(args.input_views), resolution=args.resolution,
        mesh=not args.no_mesh, mesh_resolution=args.mesh_resolution,
        mesh_threshold=parse_level(args.mesh_threshold),
        geometry=GeometryConfig(n_points=args.mesh_points, tau=args.fscore_tau), save_renders=args.save_renders,
        choices=choices, method=args.method, lpips=LpipsConfig(trunk_path=args.lpips_trunk),
        progress=not args.no_progress, overwrite=args.overwrite)
    return out, cfg, guided


def run(args: argparse.Namespace) -> int:
    """Under torchrun a refusal prints once: one from the command line alone (every rank refuses alike) by rank
    0; the output folder, checkpoint and data are checked by every rank and agreed on
    (:func:`~depthnerf.distributed.checked_together`); one rank's failure while scoring is that rank's line."""
    from depthnerf.distributed import peer_failure, teardown
    from depthnerf.errors import RefusedOnMain, launch_rank, refusal

    try:
        request = _request(args)
    except DepthnerfError as err:
        raise refusal(str(err), launch_rank()) from None
    info = _process(args.device)
    try:
        with peer_failure(info, "evaluating (the finished objects are kept: the same command continues)"):
            return _run(args, info, *request)
    except RefusedOnMain:
        return 2  # rank 0 prints why
    finally:
        teardown(info)


def _session(args: argparse.Namespace, info, out: Path, guided):
    """The output folder checked, the checkpoint loaded and its data checked: the evaluation's session."""
    from depthnerf.data.records import in_dataset
    from depthnerf.infer.session import InferenceSession, SessionOptions
    from depthnerf.pretrained.load import load_pretrained
    from depthnerf.reconstruct.exports import check_output_dir

    check_output_dir(out, overwrite=True)  # a file or an unwritable folder fails before anything loads
    pre = load_pretrained(args.run if args.run is not None else args.checkpoint, info.device)
    note = symmetry_note(args, pre.model.cfg.mirror, str(args.run or args.checkpoint))
    if note is not None and info.is_main:
        print(note, file=sys.stderr, flush=True)
    if args.data is None and pre.data_root is None:
        raise DepthnerfError(f"{pre.path}: records no training data root; pass --data DIR")
    data = args.data or Path(pre.data_root)
    if in_dataset(out, data):  # its folders would be read as objects or splits of the dataset
        raise DepthnerfError(f"{out}: --out is the dataset {data} or lies in one of its split folders, which eval "
                             "reads; choose an --out outside them")
    check_category(data, args.category, args.split, pre.spec.category, str(args.run or args.checkpoint),
                   warn=info.is_main)
    if args.strict:  # the protocol checks every file itself (leniently); this makes optional parts strict too
        from depthnerf.data.srn import index_split

        index_split(data, args.category or pre.spec.category, args.split, strict=True)
    return InferenceSession(pre, SessionOptions(
        device=info.device, depth=args.depth, depth_checkpoint=args.depth_checkpoint, inputs="dataset",
        data_root=data, fp32=args.fp32, compile=args.compile, compile_mode=args.compile_mode,
        bf16_residual=args.bf16_residual, gather=args.gather, chunk=args.chunk, guided=guided,
        samples=None if args.samples is None else tuple(args.samples), pixel_center=args.pixel_center,
        encoder_norm=args.encoder_norm, symmetry=not args.no_symmetry,
        symmetry_plane=None if args.symmetry_plane is None else tuple(args.symmetry_plane)))


def _run(args: argparse.Namespace, info, out: Path, cfg, guided) -> int:
    from depthnerf.distributed import checked_together
    from depthnerf.eval.protocol import evaluate_protocol
    from depthnerf.train.memory import one_line_out_of_memory

    with checked_together(info, "checking the output folder, the checkpoint and the data"):  # agreed: one line
        session = _session(args, info, out, guided)
    with one_line_out_of_memory(info, lambda: (
            f"evaluating at --resolution {cfg.resolution or session.spec.resolution}, --chunk {session.chunk} rays "
            f"per pass{f', --mesh-resolution {cfg.mesh_resolution}' if cfg.mesh else ''}; lower them (the finished "
            "objects are kept: the same command continues)")):
        result = evaluate_protocol(session, out, cfg, info)
    if result is None:  # a rank other than 0: rank 0 writes and prints
        return 0
    s = result.summary
    lp = f"{s['lpips']:.4f}" if s["lpips"] is not None else s["lpips_status"]
    geo = (f", Chamfer-L1 {s['chamfer_l1']:.4f}, F-score@{s['fscore_tau']} {s['fscore']:.3f}{empty_meshes_text(s)}"
           if s.get("chamfer_l1") is not None else f", mesh: {s['mesh_status']}")
    print(f"{s['method']} / {s['category']}: PSNR {s['psnr']:.3f}, SSIM {s['ssim']:.4f}, LPIPS {lp}{geo} "
          f"({s['objects']} objects, {s['views']} views, {s['timing']['total_s']:.1f} s)")
    print(f"protocol: {s['protocol']}")
    print(f"wrote {result.summary_path} and {result.per_object_path}")
    return 0
