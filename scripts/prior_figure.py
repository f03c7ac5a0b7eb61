"""Depth priors side by side: input view, ground-truth disparity and each bundled depth net's prediction.

    python scripts/prior_figure.py --data study/data --categories cars chairs --objects 3 --view 64 \
        --weights legacy=legacy srn=srn --out docs/figures/depth_net_priors.png

Each panel shows disparity (larger = closer) on the view's foreground only, coloured by its own range (a relative
prior has no scale), so the panels compare shape, not values. The AbsRel under each prediction is the view's
(least-squares scale-and-shift alignment in disparity on the foreground, ``depthnerf.depth.metrics``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from depthnerf.data.card import INTEGER_CENTRED  # noqa: E402
from depthnerf.data.srn import index_split, load_object  # noqa: E402
from depthnerf.depth.bundled import BundledEstimator  # noqa: E402
from depthnerf.depth.metrics import affine_invariant_scores  # noqa: E402


def parse_weights(items: list[str]) -> list[tuple[str, str | None]]:
    """``label=weights`` pairs: a shipped net's name (``srn``, ``legacy``), a weights file, or ``default`` (the
    default net)."""
    out = []
    for item in items:
        label, sep, path = item.partition("=")
        if not sep or not label or not path:
            raise SystemExit(f"error: --weights {item!r}: expected LABEL=WEIGHTS (a shipped net's "
                             "name, a weights file, or 'default')")
        out.append((label, None if path == "default" else path))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, nargs="+", required=True,
                   help="dataset roots; each category is read from the first that has <category>_<split>/")
    p.add_argument("--categories", nargs="+", default=["cars", "chairs"])
    p.add_argument("--split", default="test")
    p.add_argument("--objects", type=int, default=3, help="first N objects per category")
    p.add_argument("--view", type=int, default=64, help="view index (64: the SRN protocol's input view)")
    p.add_argument("--weights", nargs="+", default=["shipped=default"],
                   help="LABEL=WEIGHTS of each bundled net (a shipped net's name, a weights file or 'default')")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    nets = [(label, BundledEstimator.load(path)) for label, path in parse_weights(args.weights)]
    rows = []
    for category in args.categories:
        roots = [root for root in args.data if (root / f"{category}_{args.split}").is_dir()]
        if not roots:
            raise SystemExit(f"error: no {category}_{args.split}/ in {', '.join(map(str, args.data))}")
        for k, record in enumerate(index_split(roots[0], category, args.split).objects[:args.objects]):
            obj = load_object(record, with_depth=True, pixel_center=INTEGER_CENTRED)
            if not 0 <= args.view < obj.images.shape[0]:
                raise SystemExit(f"error: {record.object_id}: no view {args.view} ({obj.images.shape[0]} views)")
            image, z = obj.images[args.view], obj.depths[args.view]
            mask = z > 0
            truth = torch.where(mask, 1.0 / z.clamp_min(1e-6), torch.zeros_like(z))
            preds = [(label, net.predict(image[None])[0]) for label, net in nets]
            rows.append((f"{category} {k}, view {args.view}", image, mask, truth, z, preds))
    cols = 2 + len(nets)
    fig, axes = plt.subplots(len(rows), cols, figsize=(2.0 * cols, 2.1 * len(rows)), squeeze=False)
    for r, (name, image, mask, truth, z, preds) in enumerate(rows):
        panels = [("input", image.permute(1, 2, 0).numpy(), ""), ("ground truth", truth, "")]
        for label, pred in preds:
            absrel = float(affine_invariant_scores(pred[None], z[None]).abs_rel[0])
            panels.append((label, pred, f"AbsRel {absrel:.3f}"))
        for c, (title, img, note) in enumerate(panels):
            ax = axes[r, c]
            if c == 0:
                ax.imshow(img)
                ax.set_ylabel(name, fontsize=7)
            else:
                ax.imshow(np.where(mask.numpy(), np.asarray(img), np.nan), cmap="magma")
            ax.set_xticks([]), ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
            ax.set_xlabel(note, fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out} ({len(rows)} views x {cols} panels)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
