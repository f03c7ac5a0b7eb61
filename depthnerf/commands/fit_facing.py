"""``depthnerf fit-facing``: fit a mirror model's facing head and write the checkpoint with it.

``depthnerf fit-facing --checkpoint C --data DIR --category C --out FILE [--overwrite] [--split train]
[--objects 300] [--views-per-object 8] [--inputs both|dataset|photo] [--grid 4] [--seed 0] [--device cpu]
[--json PATH]``

The head reads the angle of the object's mirror plane from the input view's features
(:mod:`depthnerf.model.facing_head`); ``reconstruct --facing auto`` then takes the plane it reads
(:mod:`depthnerf.infer.facing`). It is fitted on dataset views whose plane is known
(:mod:`depthnerf.train.facing_head`; ``--inputs``: encoded as the evaluation encodes them, framed as
``reconstruct`` frames a photo, or both ways) and written into ``--out``: the checkpoint's weights file with the
head added (any head it had is replaced). ``--out`` is never the checkpoint's own file, and an existing file
only with ``--overwrite``; it, ``--json`` and ``--device`` are checked before any work, and the data must be of the
model's category. Prints the fit's size and memory before any view is encoded (a fit larger than all of the host's
memory is refused), then, per ridge weight tried, the median and 90th-percentile angle error on the held-out
objects; ``--json`` writes them with the head's description.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.files import file_problem, write_text_atomic
from depthnerf.train.facing_head import INPUTS


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", required=True, help="a mirror model: shipped name, run folder or weights file")
    p.add_argument("--data", type=Path, required=True, help="dataset root with the category's split and prior cache")
    p.add_argument("--category", required=True, help="category folder prefix, e.g. cars")
    p.add_argument("--out", type=Path, required=True,
                   help="weights file to write (the checkpoint + the head); not the checkpoint's own file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--split", choices=("train", "val", "test"), default="train", help="split (default train)")
    p.add_argument("--objects", type=int, default=300, help="at most N objects (default 300)")
    p.add_argument("--views-per-object", type=int, default=8, help="views drawn per object (default 8)")
    p.add_argument("--inputs", choices=INPUTS, default="both",
                   help="encode each view both as the dataset view and framed as reconstruct frames a photo "
                   "(default), or only one way")
    p.add_argument("--grid", type=int, default=4, help="pooling grid of the head (default 4: 4 x 4 cells)")
    p.add_argument("--seed", type=int, default=0, help="seed of the view draw and the held-out objects")
    p.add_argument("--device", default="cpu", help="torch device (cpu, cuda, cuda:N)")
    p.add_argument("--json", type=Path, default=None, help="also write the validation scores here")


def run(args: argparse.Namespace) -> int:
    from depthnerf.distributed import pick_device
    from depthnerf.pretrained.load import resolve_checkpoint
    from depthnerf.pretrained.weights import save_with_head
    from depthnerf.train.facing_head import FacingHeadConfig, fit_facing_head

    for flag, value, low in (("--objects", args.objects, 5), ("--views-per-object", args.views_per_object, 1),
                             ("--grid", args.grid, 1), ("--seed", args.seed, 0)):
        if value < low:
            raise DepthnerfError(f"{flag} must be >= {low}, got {value}")
    if args.out.suffix != ".safetensors":
        raise DepthnerfError(f"--out {args.out}: write a .safetensors file")
    pick_device(args.device, auto=False)  # a device this process lacks: one line naming the flag, before any work
    source = resolve_checkpoint(args.checkpoint)
    check_outputs(args, Path(source))
    cfg = FacingHeadConfig(data=args.data, category=args.category, split=args.split, objects=args.objects,
                           views_per_object=args.views_per_object, grid=args.grid, seed=args.seed, device=args.device,
                           inputs=args.inputs)
    fit = fit_facing_head(source, cfg, log=lambda line: print(line, file=sys.stderr, flush=True))
    for lam, score in fit.validation.items():
        chosen = "  <- chosen" if float(lam) == fit.head.info["lambda"] else ""
        print(f"lambda {lam:>6}: held-out |angle error| median {score['median_deg']:.2f} deg, "
              f"90th percentile {score['p90_deg']:.2f} deg{chosen}")
    try:
        save_with_head(source, fit.head, args.out)
    except OSError as err:
        raise DepthnerfError(f"{args.out}: cannot write ({err.strerror or err})") from None
    if args.json is not None:
        try:
            write_text_atomic(args.json, json.dumps({"head": fit.head.describe(), "validation": fit.validation},
                                                    indent=2) + "\n")
        except OSError as err:
            raise DepthnerfError(f"{args.json}: cannot write the scores ({err.strerror or err})") from None
    print(f"wrote {args.out}: {args.checkpoint} with a facing head fitted on {fit.head.info['views']} views of "
          f"{fit.head.info['objects']} objects ({fit.head.info['data']})")
    return 0


def check_outputs(args: argparse.Namespace, source: Path) -> None:
    """Refuse, before any work, an ``--out`` or ``--json`` that cannot be written (:func:`file_problem`), an
    ``--out`` that is the checkpoint's own weights file ``source`` or an existing file without ``--overwrite``, and
    a ``--json`` that is ``--out``."""
    for flag, path in (("--out", args.out), ("--json", args.json)):
        if path is not None and (problem := file_problem(path, flag)) is not None:
            raise DepthnerfError(problem)
    out = args.out.resolve()
    if out == source.resolve():
        raise DepthnerfError(f"{args.out}: --out is the checkpoint's own weights file; write the checkpoint with "
                             "its head to another file")
    if args.json is not None and args.json.resolve() == out:
        raise DepthnerfError(f"{args.json}: --json names the --out file; give the scores another file")
    if args.out.exists() and not args.overwrite:
        raise DepthnerfError(f"{args.out}: exists; pass --overwrite to replace it, or choose another --out")
