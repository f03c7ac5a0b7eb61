"""``depthnerf synth``: generate the procedural SRN-protocol benchmark (cars or chairs).

Example: ``depthnerf synth --category cars --out data/synth --train-objects 20 --val-objects 5 --test-objects 5``
writes ``data/synth/cars_{train,val,test}/<object_id>/...`` (SRN layout plus depth, masks and meshes) and
``data/synth/cars_card.json``. Re-running the same command resumes: finished objects are skipped.
``--framing srn`` (default) frames objects as SRN's renderer does, ``--framing legacy`` as generator 1 (the data of
an earlier set of shipped checkpoints); ``--family heldout`` draws car and chair styles the standard family never does.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from depthnerf.data.synth.framing import DEFAULT_FRAMING, FRAMINGS
from depthnerf.data.synth.generate import FAMILIES, SynthConfig, generate
from depthnerf.data.synth.hits import ENGINES
from depthnerf.data.synth.raycast import SynthRenderConfig
from depthnerf.errors import DepthnerfError
from depthnerf.train.memory import failed_allocation, is_out_of_memory


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--category", required=True, choices=["cars", "chairs"], help="object category")
    parser.add_argument("--out", required=True, type=Path, help="dataset root directory")
    parser.add_argument("--train-objects", type=int, default=20, help="train objects, 50 views each (default 20)")
    parser.add_argument("--val-objects", type=int, default=5, help="val objects, 251 views each (default 5)")
    parser.add_argument("--test-objects", type=int, default=5, help="test objects, 251 views each (default 5)")
    parser.add_argument("--resolution", type=int, default=128, help="image size in pixels (default 128, as SRN)")
    parser.add_argument("--seed", type=int, default=0, help="master seed (default 0)")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--views-train", type=int, default=50, help="views per train object (SRN: 50)")
    parser.add_argument("--views-test", type=int, default=251, help="views per val/test object (SRN: 251)")
    parser.add_argument("--no-antialias", action="store_true", help="one ray per pixel for RGB too")
    parser.add_argument("--framing", choices=sorted(FRAMINGS), default=DEFAULT_FRAMING,
                        help="srn: frame objects as SRN's renderer (unit diagonal, SRN spiral with view 64 a side "
                             "view, Blender pixel centres; generator depthnerf-synth-2, default; the shipped cpu-* "
                             "checkpoints' training data); legacy: generator depthnerf-synth-1 (docs/data.md)")
    parser.add_argument("--family", choices=list(FAMILIES), default="standard",
                        help="shape family: standard, or heldout (car/chair styles the standard family never "
                             "draws, for generalisation checks)")
    parser.add_argument("--raycaster", choices=list(ENGINES), default="auto",
                        help="first-hit engine: embree (embreex; fast on a CPU), torch (brute force, on CUDA when "
                             "there is one; needs no embreex) or auto (embree where embreex imports, else torch; "
                             "default). The same images up to ties on shared triangle edges")
    parser.add_argument("--no-progress", "--quiet", dest="no_progress", action="store_true",
                        help="no progress bar (the name every other command uses; --quiet is the same flag)")


def run(args: argparse.Namespace) -> int:
    config = SynthConfig(
        category=args.category, out=args.out, train_objects=args.train_objects, val_objects=args.val_objects,
        test_objects=args.test_objects, resolution=args.resolution, seed=args.seed, workers=args.workers,
        views_train=args.views_train, views_test=args.views_test,
        render=SynthRenderConfig(antialias=not args.no_antialias), progress=not args.no_progress, framing=args.framing,
        family=args.family, raycaster=args.raycaster,
    )
    try:
        card = generate(config)
    except (RuntimeError, MemoryError) as err:  # a huge --resolution: one line, not the allocator's traceback
        if not is_out_of_memory(err):
            raise
        raise DepthnerfError(f"out of memory ({failed_allocation(err)}) rendering {args.category} at --resolution "
                             f"{args.resolution} (--views-train {args.views_train}, --views-test {args.views_test}); "
                             f"lower them (finished objects in {args.out} are kept)") from None
    counts = ", ".join(f"{k} {v}" for k, v in card["counts"].items())
    print(f"wrote {args.category} ({counts}) to {args.out}; card: {args.out / (args.category + '_card.json')}")
    return 0
