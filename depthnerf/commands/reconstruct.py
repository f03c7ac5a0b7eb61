"""``depthnerf reconstruct IMAGE --checkpoint CKPT --out DIR``: one photo -> depth prior, novel views, turntable,
depth maps, mesh and point cloud (a thin layer over :class:`depthnerf.reconstruct.reconstructor.Reconstructor`).

The photo should show one object, roughly centred; the mask is ``--mask``, else the alpha channel, else a
background model's cut-out when one is installed (``--background-removal``, ``--background-model``;
:mod:`depthnerf.reconstruct.background`), else everything that differs from the border colour (rules, framing
and camera defaults in :mod:`depthnerf.reconstruct.reconstructor`; the output layout in
:mod:`depthnerf.reconstruct.exports`).
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from depthnerf.commands.evaluate import (
    add_guided_flags,
    add_precision_flags,
    add_samples_flag,
    guided_request,
)
from depthnerf.depth.estimators import PHOTO_ESTIMATORS
from depthnerf.distributed import pick_device
from depthnerf.errors import DepthnerfError
from depthnerf.infer.facing import AUTO, MIN_CONFIDENCE
from depthnerf.reconstruct.background import DEFAULT_MODEL, MODES, NAMED_MODELS
from depthnerf.render.config import DEFAULT_BUDGET
from depthnerf.render.mesh_colors import MESH_COLOR_RULES
from depthnerf.render.photo_colors import PHOTO_FILL


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("image", type=Path, help="input photo (RGB, RGBA or grayscale)")
    p.add_argument("--checkpoint", required=True,
                   help="model weights: weights file, checkpoint/run folder, shipped name or Hub file "
                        "hf://OWNER/REPO[/FILE][@REVISION]")
    p.add_argument("--out", type=Path, required=True,
                   help="output folder (manifest.json lists every file); checked before any work")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an earlier reconstruction in --out (only the files reconstruct writes)")
    p.add_argument("--mask", type=Path,
                   help="object mask, same size as the image (object: values above half the mask's maximum, so "
                        "0/1 and 0/255 masks both work)")
    p.add_argument("--background-removal", choices=MODES, default="auto",
                   help="remove the background of a photo without alpha or mask with a rembg model: auto (default: "
                        "when rembg and the model are installed, pip install 'depthnerf[bg]'), on, off")
    p.add_argument("--background-model", metavar="NAME_OR_FILE",
                   help=f"rembg model name ({', '.join(NAMED_MODELS)}; default {DEFAULT_MODEL}) from rembg's model "
                        "folder (rembg's download_models fetches one there), or a U^2-Net-style .onnx file")
    p.add_argument("--views", type=int, default=36, help="novel views on the orbit (default 36)")
    p.add_argument("--elevation", type=float, default=20.0, help="input camera elevation, degrees (default 20)")
    p.add_argument("--radius", type=float, help="camera distance (default: the training category's)")
    p.add_argument("--focal", type=float,
                   help="focal length in pixels of a 128 px frame (default: the training category's, SRN 131.25)")
    p.add_argument("--framing", choices=["auto", "keep"], default="auto",
                   help="auto (default): crop around the object to --fill; keep: only pad to square")
    p.add_argument("--fill", type=float, help="object's longer side / frame side with --framing auto (default: the "
                   "fill of the checkpoint's training data)")
    p.add_argument("--facing", type=_facing, default=argparse.SUPPRESS, metavar="DEG|auto|none",
                   help="mirror models: which way the object's front points, degrees from the camera towards the "
                        "image's right (0 = facing the camera, 90 = facing right, 270 = left; default 90, a side "
                        "view; a few degrees off costs more than no plane); auto = estimated from the photo (read by "
                        "the checkpoint's facing head when it has one, else the plane whose render of the photo is "
                        "closest, or none); none = no symmetry plane")
    p.add_argument("--facing-min-confidence", type=float, default=argparse.SUPPRESS, metavar="C",
                   help="--facing auto with a facing head: no plane where the head's confidence in its reading "
                        f"(printed; about 1 when sure) is below C (default {MIN_CONFIDENCE:g}: the head's plane always)")
    p.add_argument("--render-resolution", type=int, help="side of the rendered views (default: training res)")
    p.add_argument("--mesh-resolution", type=int, default=128,
                   help="marching-cubes grid samples (default 128; 0 = no mesh)")
    p.add_argument("--mesh-threshold", default=argparse.SUPPRESS,
                   help="marching-cubes density level: a number, local (default: half the peak density along each "
                        "input ray, between the auto and silhouette levels on the mask's rays, auto elsewhere: "
                        "keeps thin parts), auto (half the median peak density along the opaque input rays: one "
                        "tight surface) or silhouette (the level whose input-view outline best matches the input's "
                        "mask: a thicker surface)")
    p.add_argument("--mesh-keep", choices=["all", "largest"], default=argparse.SUPPRESS,
                   help="all pieces of the mesh (default), or only the largest connected piece; manifest.json "
                        "records the pieces and faces either way")
    p.add_argument("--mesh-colors", choices=MESH_COLOR_RULES, default=argparse.SUPPRESS,
                   help="vertex colours: photo (default: the photo's colour where it sees the vertex or, for a "
                        "mirror model, its mirror image; elsewhere normal-ray's), normal-ray (the colour the "
                        "renderer gives a short ray into the surface along its normal) or point (the network's "
                        "colour at the vertex, seen from the input camera; speckled)")
    p.add_argument("--mesh-fill", type=float, default=argparse.SUPPRESS,
                   help="photo colours: how far the photo's colours spread over the surface into what it does not "
                        "see, in world units per unit of the network's RMS colour error where it sees (default "
                        f"{PHOTO_FILL:g}; 0: the network's colours there)")
    p.add_argument("--depth", "--depth-estimator", dest="depth", choices=PHOTO_ESTIMATORS,
                   help="override the checkpoint's depth prior (needed for checkpoints trained with oracle; "
                        "--depth-estimator: same)")
    p.add_argument("--depth-checkpoint", help="depth estimator weights (hub id / local dir / weights file)")
    add_guided_flags(p, _budget)
    add_samples_flag(p)
    p.add_argument("--chunk", type=int, help="rays per render pass (default 4096 on CPU, 65536 on CUDA)")
    p.add_argument("--device", default="auto", help="auto (CUDA if available), cpu, cuda or cuda:N")
    add_precision_flags(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _budget(text: str) -> int:
    """``--guided``'s optional sample budget; a word that is not a number is most likely the image path."""
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a sample budget (an integer), got {text!r}; for the default budget put --guided after the "
            f"image, or write --guided {DEFAULT_BUDGET}") from None


def _facing(text: str) -> float | str | None:
    """``--facing``: an angle in degrees, ``auto`` or ``none``."""
    if text.strip().lower() == "none":
        return None
    if text.strip().lower() == AUTO:
        return AUTO
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an angle in degrees, 'auto' or 'none', got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite angle in degrees, got {text!r}")
    return value


MESH_FLAGS = ("mesh_threshold", "mesh_keep", "mesh_colors", "mesh_fill")
"""The mesh flags (argparse ``dest``) beside ``--mesh-resolution``: their defaults are argparse-suppressed, so a
flag is in the namespace only when given (:func:`given_mesh_flags`); else the default of
:class:`~depthnerf.reconstruct.reconstructor.ReconstructConfig` holds."""


def given_mesh_flags(args: argparse.Namespace) -> dict[str, object]:
    """The :data:`MESH_FLAGS` given on the command line, by ``dest``, as they were given."""
    return {dest: getattr(args, dest) for dest in MESH_FLAGS if hasattr(args, dest)}


def check_flags(args: argparse.Namespace) -> None:
    """One line for a flag that another flag turns off (it would be accepted and do nothing): ``--fill`` with
    ``--framing keep``, ``--background-model`` with ``--background-removal off``, ``--facing-min-confidence``
    without ``--facing auto``, a mesh flag with ``--mesh-resolution 0`` (no mesh)."""
    given = ["--" + dest.replace("_", "-") for dest in given_mesh_flags(args)]
    if args.mesh_resolution == 0 and given:
        raise DepthnerfError(f"{' '.join(given)} {'applies' if len(given) == 1 else 'apply'} only to the mesh, which "
                             "--mesh-resolution 0 skips: pass one or the other")
    if args.fill is not None and args.framing == "keep":
        raise DepthnerfError("--fill applies only with --framing auto (keep only pads the photo to a square)")
    if args.background_model is not None and args.background_removal == "off":
        raise DepthnerfError("--background-model applies only when the background is removed (drop "
                             "--background-removal off)")
    if hasattr(args, "facing_min_confidence") and getattr(args, "facing", None) != AUTO:
        raise DepthnerfError("--facing-min-confidence applies only with --facing auto")


def run(args: argparse.Namespace) -> int:
    from depthnerf.distributed import DistInfo
    from depthnerf.infer.session import InferenceSession, SessionOptions
    from depthnerf.reconstruct.background import choose_remover
    from depthnerf.reconstruct.exports import check_output_dir
    from depthnerf.reconstruct.photo import check_image_file
    from depthnerf.reconstruct.reconstructor import DEFAULT_FACING, ReconstructConfig, Reconstructor
    from depthnerf.render.mesh_level import parse_level
    from depthnerf.train.memory import one_line_out_of_memory

    # every flag and the output folder are checked before the model is loaded or anything rendered
    mesh = given_mesh_flags(args)  # the others keep ReconstructConfig's defaults
    if "mesh_threshold" in mesh:
        mesh["mesh_threshold"] = parse_level(mesh["mesh_threshold"])
    cfg = ReconstructConfig(views=args.views, elevation=args.elevation, radius=args.radius, focal=args.focal,
                            framing=args.framing, fill=args.fill, render_resolution=args.render_resolution,
                            mesh_resolution=args.mesh_resolution, **mesh,
                            progress=not args.no_progress, background_removal=args.background_removal,
                            background_model=args.background_model,
                            facing=getattr(args, "facing", DEFAULT_FACING),
                            facing_min_confidence=getattr(args, "facing_min_confidence", MIN_CONFIDENCE))
    check_flags(args)
    options = SessionOptions(device=pick_device(args.device), depth=args.depth,
                             depth_checkpoint=args.depth_checkpoint, fp32=args.fp32, compile=args.compile,
                             compile_mode=args.compile_mode, bf16_residual=args.bf16_residual, gather=args.gather,
                             chunk=args.chunk, guided=guided_request(args.guided, args.guided_align_samples),
                             samples=None if args.samples is None else tuple(args.samples))
    check_output_dir(args.out, args.overwrite, [p for p in (args.image, args.mask) if p is not None])
    check_image_file(args.image)  # a missing or non-image photo / mask fails before any model loads
    if args.mask is not None:
        check_image_file(args.mask, "mask")
    # a background model the flags name loads (or fails in one line) before the NeRF does
    background = choose_remover(args.background_removal, args.background_model)
    rec = Reconstructor(InferenceSession(args.checkpoint, options))
    side = cfg.render_resolution or rec.session.spec.resolution
    with one_line_out_of_memory(DistInfo(rank=0, world=1, device=rec.session.device), lambda: (
            f"reconstructing {args.image}: {cfg.views} views at --render-resolution {side}, --chunk "
            f"{rec.session.chunk} rays per pass, --mesh-resolution {cfg.mesh_resolution}; lower them")):
        result = rec.reconstruct(args.image, mask=args.mask, config=cfg, background=background)
    manifest = rec.save(result, args.out)
    for note in result.input.notes:
        print(f"note: {note}")
    if rec.session.model.cfg.mirror:
        print(f"note: symmetry {result.settings['symmetry']}")
    elif hasattr(args, "facing"):
        print(f"note: --facing has no effect: {args.checkpoint} has no mirror-symmetric conditioning", file=sys.stderr)
    mesh = manifest["mesh"]
    made = (f"mesh ({mesh['faces']} faces{', empty' if mesh['empty'] else ''})" if mesh["made"]
            else "no mesh (--mesh-resolution 0)")
    print(f"wrote {len(manifest['files']['views'])} views, turntable, {made}, "
          f"{manifest['point_cloud']['points']} points to {args.out} (manifest: {args.out / 'manifest.json'})")
    return 0
