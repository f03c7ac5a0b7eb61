"""Qualitative comparison grid: input view, its depth prior, ground truth and each method's render of one target.

    python scripts/qualitative_figure.py --evals STUDY/eval/cars-none STUDY/eval/cars-bundled \\
        STUDY/eval/cars-oracle --data STUDY/data --out STUDY/figures/qualitative_cars.png --objects 4

Input: output folders of ``depthnerf eval ... --save-renders`` for one category (see
:mod:`depthnerf.eval.protocol`): ``summary.json`` (method label, category, split, depth prior and its provenance,
input resolution), ``per_object.csv`` (each object's input view) and ``renders.csv`` (``object_id, view,
render_path, gt_path, psnr, ssim``; paths relative to the eval folder unless absolute). An eval folder without
``renders.csv`` is an error (rerun ``depthnerf eval`` with ``--save-renders``).

One row per object: the first ``--objects`` objects (in the first eval's order) that every eval rendered, or
``--object-ids``. Columns: the input view (the protocol's view 64, from ``--data`` at the input resolution the
model saw), the depth prior of that view for every depth-aware prior among the evals (read through
:class:`~depthnerf.depth.cache.PriorStore` opened with the estimator, weights and resolution the summary records,
so a stale or missing cache is an error; colour-mapped between the 1st and 99th percentiles of its values on
the object's mask, bright = near, background white as the model sees a constant there),
the ground-truth target (the eval's ``gt_path``), then each eval's render of that target with its per-view PSNR
from ``renders.csv`` under it. The target is ``--view`` (it must have been rendered by every eval; with
``--views-stride K`` only every K-th view was), else the first view every eval rendered for that object.

Output: ``FIG.png`` (Agg backend) and ``FIG.csv`` beside it: one row per cell, ``object_id,column,view,psnr,
source`` (``source`` = the image file or prior cache the cell shows; ``psnr`` copied from ``renders.csv``).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
import textwrap
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from depthnerf.data import srn_format
from depthnerf.data.card import INTEGER_CENTRED
from depthnerf.data.srn import ObjectRecord, index_split, load_object
from depthnerf.depth.cache import CachedPriorStore, PriorStore, object_path
from depthnerf.depth.prior import PriorConfig, portable_prior
from depthnerf.errors import DepthnerfError

PRIOR_CMAP = "magma"
"""Colour map of the depth priors (relative disparity: bright = near)."""
CSV_COLUMNS = ("object_id", "column", "view", "psnr", "source")
"""Columns of ``FIG.csv``."""


@dataclass(frozen=True)
class RenderRow:
    """One line of an eval folder's ``renders.csv``, paths resolved."""

    render: Path
    """The rendered PNG."""
    gt: Path
    """The ground-truth PNG it was scored against."""
    psnr: float
    """PSNR of the view (dB), as the eval computed it."""


@dataclass(frozen=True)
class EvalDir:
    """What the figure needs from one ``depthnerf eval`` output folder."""

    path: Path
    """The folder."""
    summary: dict
    """Its ``summary.json``."""
    input_views: dict[str, int]
    """Object id -> input view (``per_object.csv``)."""
    renders: dict[tuple[str, int], RenderRow]
    """(object id, view) -> rendered view."""
    objects: tuple[str, ...]
    """Object ids with renders, in file order."""

    @property
    def method(self) -> str:
        """Column title of its renders."""
        return str(self.summary.get("method") or self.path.name)


@dataclass(frozen=True)
class Cell:
    """One image of the grid."""

    column: str
    """Column title."""
    image: np.ndarray
    """``H x W x 3`` float in [0, 1]."""
    view: int
    """Dataset view index shown."""
    source: str
    """File (or prior cache file) the image comes from."""
    psnr: float | None = None
    """PSNR of a render (None for the other columns)."""


def _read_csv(path: Path, required: Sequence[str], hint: str) -> list[dict]:
    if not path.is_file():
        raise DepthnerfError(f"{path}: missing; {hint}")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    missing = [c for c in required if rows and c not in rows[0]]
    if not rows or missing:
        raise DepthnerfError(f"{path}: no rows or missing columns {', '.join(missing) or '(empty file)'}")
    return rows


def load_eval_dir(path: Path) -> EvalDir:
    """Read ``summary.json``, ``per_object.csv`` and ``renders.csv`` of an eval folder."""
    path = Path(path)
    summary_path = path / "summary.json"
    try:
        summary = json.loads(summary_path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise DepthnerfError(f"{summary_path}: unreadable eval summary ({err})") from None
    for key in ("category", "split", "depth_prior", "input_resolution"):
        if key not in summary:
            raise DepthnerfError(f"{summary_path}: no '{key}' (not written by depthnerf eval)")
    rerun = "rerun depthnerf eval with --save-renders"
    per_object = _read_csv(path / "per_object.csv", ("object_id", "input_view"), rerun)
    rows = _read_csv(path / "renders.csv", ("object_id", "view", "render_path", "gt_path", "psnr"), rerun)
    renders, objects = {}, []
    for row in rows:
        try:
            key = (row["object_id"], int(row["view"]))
            renders[key] = RenderRow(render=path / row["render_path"], gt=path / row["gt_path"],
                                     psnr=float(row["psnr"]))
        except ValueError:
            raise DepthnerfError(f"{path / 'renders.csv'}: bad view or psnr in row {row}") from None
        objects += [row["object_id"]] if row["object_id"] not in objects else []
    return EvalDir(path=path, summary=summary, renders=renders, objects=tuple(objects),
                   input_views={r["object_id"]: int(r["input_view"]) for r in per_object})


def choose_objects(evals: Sequence[EvalDir], count: int, ids: Sequence[str] | None) -> list[str]:
    """``ids`` (each rendered by every eval), else the first ``count`` objects every eval rendered."""
    common = [o for o in evals[0].objects if all(o in e.objects for e in evals[1:])]
    if ids:
        for object_id in ids:
            lacking = [str(e.path) for e in evals if object_id not in e.objects]
            if lacking:
                raise DepthnerfError(f"{lacking[0]}/renders.csv: object {object_id} was not rendered")
        return list(ids)
    if count < 1:
        raise DepthnerfError(f"--objects must be >= 1, got {count}")
    if not common:
        raise DepthnerfError(f"{evals[0].path}: no object was rendered by every eval folder (same split?)")
    return common[:count]


def choose_view(evals: Sequence[EvalDir], object_id: str, view: int | None) -> int:
    """``view`` (rendered by every eval), else the first view of ``object_id`` every eval rendered."""
    views = sorted(v for (o, v) in evals[0].renders if o == object_id)
    common = [v for v in views if all((object_id, v) in e.renders for e in evals[1:])]
    if view is not None:
        lacking = [e for e in evals if (object_id, view) not in e.renders]
        if lacking:
            shown = [v for (o, v) in sorted(lacking[0].renders) if o == object_id][:8]
            raise DepthnerfError(f"{lacking[0].path}/renders.csv: view {view} of {object_id} was not rendered "
                                 f"(rendered: {', '.join(map(str, shown))}, ...)")
        return view
    if not common:
        raise DepthnerfError(f"{evals[0].path}: no target view of {object_id} was rendered by every eval folder")
    return common[0]


def prior_key(ev: EvalDir) -> tuple[str, str | None]:
    """``(estimator, weights hash)`` of a depth-aware eval: the evals that read the same prior share a column."""
    provenance = ev.summary.get("depth_prior_provenance")
    return ev.summary["depth_prior"], provenance.get("weights_hash") if isinstance(provenance, dict) else None


def open_prior_store(ev: EvalDir, data_root: Path) -> PriorStore:
    """The prior store of a depth-aware eval, from its summary's estimator, weights and resolution; the weights
    are named by the hash the summary recorded (:func:`~depthnerf.depth.prior.portable_prior`: a summary written
    when its weights were the default names none), and a cache of other weights is an error."""
    summary_path = ev.path / "summary.json"
    provenance = ev.summary.get("depth_prior_provenance")
    if not isinstance(provenance, dict) or "resolution" not in provenance:
        raise DepthnerfError(f"{summary_path}: no depth_prior_provenance with a resolution for its depth prior")
    prior = portable_prior(PriorConfig(ev.summary["depth_prior"], provenance.get("checkpoint")),
                           provenance.get("weights_hash"))
    store = PriorStore.open(data_root, prior.estimator, prior.checkpoint, resolution=int(provenance["resolution"]))
    if store is None:
        raise DepthnerfError(f"{summary_path}: depth prior 'none' has no prior to show")
    served, recorded = store.provenance.get("weights_hash"), provenance.get("weights_hash")
    if recorded and served != recorded:
        raise DepthnerfError(f"{summary_path}: the eval read '{prior.estimator}' weights sha256 {recorded[:12]}..., "
                             f"the prior found for it has {str(served)[:12]}...; pass the depth weights it used")
    return store


def prior_label(key: tuple[str, str | None], store: PriorStore, keys: list[tuple[str, str | None]]) -> str:
    """``depth prior (ESTIMATOR)``, with the weights' name when two columns share the estimator."""
    estimator = key[0]
    if sum(k[0] == estimator for k in keys) == 1:
        return f"depth prior ({estimator})"
    named = store.provenance.get("checkpoint") or str(key[1])[:12]
    return f"depth prior ({estimator}, {Path(str(named)).name})"


def prior_source(store: PriorStore, record: ObjectRecord) -> str:
    """What a prior cell shows: the cache file, or the ground-truth depth map for ``oracle``."""
    if isinstance(store, CachedPriorStore):
        return str(object_path(store.root, record))
    return f"{store.provenance['estimator']}: {record.path / 'depth'}"


def colorize(disparity: np.ndarray, mask: np.ndarray | None = None, cmap: str = PRIOR_CMAP) -> np.ndarray:
    """``H x W`` relative disparity -> ``H x W x 3`` colours; limits at the 1st / 99th percentiles of the pixels
    in ``mask`` (the object, when it has any pixel; else the whole image), values beyond them clipped; pixels
    outside ``mask`` are white, because the model never sees the estimator's background values (the prior is
    set to a constant there, :func:`depthnerf.depth.normalize.normalize_disparity`)."""
    from matplotlib import colormaps

    pixels = disparity[mask] if mask is not None and mask.any() else disparity
    lo, hi = np.percentile(pixels, [1.0, 99.0])
    scaled = np.clip((disparity - lo) / max(float(hi - lo), 1e-12), 0.0, 1.0)
    rgb = colormaps[cmap](scaled)[..., :3].astype(np.float32)
    if mask is not None and mask.any():
        rgb[~mask.astype(bool)] = 1.0
    return rgb


def _record_index(data_root: Path, ev: EvalDir) -> dict[str, ObjectRecord]:
    split = index_split(data_root, ev.summary["category"], ev.summary["split"], check_files=False)
    return {r.object_id: r for r in split.objects}


def build_rows(evals: Sequence[EvalDir], data_root: Path, object_ids: Sequence[str], view: int | None
               ) -> list[list[Cell]]:
    """The grid's cells, one list per object (see the module docstring for the columns)."""
    first = evals[0]
    categories = {(e.summary["category"], e.summary["split"]) for e in evals}
    if len(categories) > 1:
        raise DepthnerfError(f"{first.path}: eval folders cover different category/split pairs {sorted(categories)}")
    records = _record_index(data_root, first)
    priors: dict[tuple[str, str | None], EvalDir] = {}
    for e in evals:
        if e.summary["depth_prior"] != "none":
            priors.setdefault(prior_key(e), e)
    stores = {key: open_prior_store(e, data_root) for key, e in priors.items()}
    labels = {key: prior_label(key, store, list(stores)) for key, store in stores.items()}
    input_res = int(first.summary["input_resolution"])
    grid = []
    for object_id in object_ids:
        if object_id not in records:
            raise DepthnerfError(f"{data_root}: object {object_id} is not in {first.summary['category']}_"
                                 f"{first.summary['split']}")
        record = records[object_id]
        inputs = {e.input_views.get(object_id) for e in evals}
        if len(inputs) != 1 or None in inputs:
            raise DepthnerfError(f"{first.path}/per_object.csv: input view of {object_id} differs across evals "
                                 f"or is missing ({sorted(map(str, inputs))})")
        src = inputs.pop()
        target = choose_view(evals, object_id, view)
        src_view = load_object(record, [src], resolution=input_res, pixel_center=INTEGER_CENTRED)  # pixels only
        cells = [Cell("input view", src_view.images[0].permute(1, 2, 0).numpy(), src, str(record.rgb_path(src)))]
        for key, store in stores.items():
            disparity = store.load(record, [src])[0].numpy()
            mask = src_view.masks[0].numpy() if disparity.shape == tuple(src_view.masks.shape[1:]) else None
            cells.append(Cell(labels[key], colorize(disparity, mask), src, prior_source(store, record)))
        gt = first.renders[(object_id, target)].gt
        cells.append(Cell("ground truth", srn_format.read_rgb(gt), target, str(gt)))
        for e in evals:
            row = e.renders[(object_id, target)]
            cells.append(Cell(e.method, srn_format.read_rgb(row.render), target, str(row.render), row.psnr))
        grid.append(cells)
    return grid


TITLE_WIDTH = 26
"""Characters per line of a column title: a column is 1.9 inches wide, and 8-point text overlapped its neighbours
beyond about 28 characters."""


def draw(object_ids: Sequence[str], grid: Sequence[Sequence[Cell]], out: Path, title: str | None = None) -> None:
    """Draw the grid into ``out`` (Agg backend, no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    rows, cols = len(grid), len(grid[0])
    fig = Figure(figsize=(1.9 * cols, 2.1 * rows + (0.4 if title else 0.0)), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False)
    for r, cells in enumerate(grid):
        for c, cell in enumerate(cells):
            ax = axes[r][c]
            ax.imshow(np.clip(cell.image, 0.0, 1.0), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title("\n".join(textwrap.wrap(cell.column, TITLE_WIDTH)), fontsize=8)  # long method names
            label = f"view {cell.view}" + (f", PSNR {cell.psnr:.2f} dB" if cell.psnr is not None else "")
            ax.set_xlabel(label, fontsize=7)
        name = object_ids[r]  # both ends: synthetic ids differ only at the end, ShapeNet hashes anywhere
        axes[r][0].set_ylabel(name if len(name) <= 16 else f"{name[:8]}...{name[-6:]}", fontsize=7)
    if title:
        fig.suptitle(title)
    fig.savefig(out, dpi=150)


def write_csv(path: Path, object_ids: Sequence[str], grid: Sequence[Sequence[Cell]]) -> None:
    """One row per cell (see the module docstring)."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(CSV_COLUMNS))
        writer.writeheader()
        for object_id, cells in zip(object_ids, grid, strict=True):
            writer.writerows({"object_id": object_id, "column": c.column, "view": c.view,
                              "psnr": "" if c.psnr is None else repr(c.psnr), "source": c.source} for c in cells)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--evals", nargs="+", type=Path, required=True, metavar="EVAL_DIR",
                        help="depthnerf eval --save-renders output folders (baseline first)")
    parser.add_argument("--data", type=Path, default=None,
                        help="dataset root (default: the first summary's data_card root)")
    parser.add_argument("--out", type=Path, required=True, help="figure file (FIG.png); FIG.csv is written beside it")
    parser.add_argument("--objects", type=int, default=3, help="number of objects (rows), default 3")
    parser.add_argument("--object-ids", nargs="+", default=None, help="these objects instead of the first N")
    parser.add_argument("--view", type=int, default=None, help="target view (default: first view all evals rendered)")
    parser.add_argument("--title", default=None, help="figure title")
    parser.add_argument("--labels", nargs="+", default=None, metavar="LABEL",
                        help="column titles of the evals' renders, one per --evals folder (default: their method)")
    args = parser.parse_args(argv)
    try:
        if args.out.suffix.lower() == ".csv":
            raise DepthnerfError(f"{args.out}: --out is the figure; its numbers go to the .csv beside it")
        evals = [load_eval_dir(p) for p in args.evals]
        if args.labels is not None:
            if len(args.labels) != len(evals):
                raise DepthnerfError(f"--labels: {len(args.labels)} labels for {len(evals)} --evals folders")
            evals = [dataclasses.replace(e, summary={**e.summary, "method": label})
                     for e, label in zip(evals, args.labels, strict=True)]
        data_root = args.data or Path(evals[0].summary.get("data_card", {}).get("root") or ".")
        object_ids = choose_objects(evals, args.objects, args.object_ids)
        grid = build_rows(evals, data_root, object_ids, args.view)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        draw(object_ids, grid, args.out, args.title)
        csv_path = args.out.with_suffix(".csv")
        write_csv(csv_path, object_ids, grid)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} and {csv_path} ({len(object_ids)} objects x {len(grid[0])} columns)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
