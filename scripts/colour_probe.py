"""Do a model's encoder features carry the input's colours? A linear probe from features to pixel colour.

Each object's input view (view 64 where it has one, else view 0) is encoded as evaluation encodes it; at every
feature pixel whose area is all object (the mask average-pooled to the feature grid is 1), the feature vector
(every stage and the depth encoder's channels) is paired with the input's colour average-pooled to that pixel. A
ridge regression (features standardised on the fit objects) is fitted on the train split's first ``--fit-objects``
objects and scored on the test split's first ``--test-objects``: R^2 per RGB channel and the RMS error. It runs once
per ``--encoder-norm`` (``running``: the BatchNorm running statistics evaluation uses; ``image``: each image's own
statistics, as per-object training normalises one source view). High R^2 means the colour is in the features
linearly, so a renderer that misses it loses it downstream.

    python scripts/colour_probe.py --checkpoint cpu-chairs-sym-pp --data DATA
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from depthnerf.data.protocol import INPUT_VIEW
from depthnerf.data.srn import index_split
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.model.config import ENCODER_NORMS
from depthnerf.pretrained.load import load_pretrained


def object_pixels(session: InferenceSession, records: list, plane) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features ``[P, C]``, colours ``[P, 3]`` and object indices ``[P]`` of every all-object feature pixel."""
    feats, colours, owners = [], [], []
    with torch.no_grad():
        for k, record in enumerate(records):
            view = INPUT_VIEW if record.num_views > INPUT_VIEW else 0
            source = session.load_views(record, [view], session.spec.resolution,
                                        with_depth=session.prior_source.needs_depths)
            maps = session.encode_views(source, symmetry_plane=plane).enc.features[0, 0]
            size = maps.shape[-2:]
            inside = F.adaptive_avg_pool2d(source.masks[0][None].float(), size)[0] >= 1.0
            colour = F.adaptive_avg_pool2d(source.images[0], size)
            feats.append(maps[:, inside].T.double().numpy())
            colours.append(colour[:, inside].T.double().numpy())
            owners.append(np.full(int(inside.sum()), k))
    return np.concatenate(feats), np.concatenate(colours), np.concatenate(owners)


def ridge_probe(x_fit: np.ndarray, y_fit: np.ndarray, x_test: np.ndarray, y_test: np.ndarray,
                alpha: float) -> dict[str, object]:
    """Ridge regression ``y ~ x`` (``x`` standardised on the fit rows, intercept unpenalised): test R^2 per output
    column and RMS error."""
    mean, std = x_fit.mean(0), x_fit.std(0) + 1e-8
    a, b = (x_fit - mean) / std, (x_test - mean) / std
    y_mean = y_fit.mean(0)
    weights = np.linalg.solve(a.T @ a + alpha * np.eye(a.shape[1]), a.T @ (y_fit - y_mean))
    pred = b @ weights + y_mean
    r2 = 1 - ((pred - y_test) ** 2).sum(0) / ((y_test - y_test.mean(0)) ** 2).sum(0)
    return {"r2": [float(v) for v in r2], "rmse": float(np.sqrt(((pred - y_test) ** 2).mean()))}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--data", required=True)
    ap.add_argument("--fit-objects", type=int, default=200, help="train-split objects the probe is fitted on")
    ap.add_argument("--test-objects", type=int, default=50, help="test-split objects it is scored on")
    ap.add_argument("--alpha", type=float, default=100.0, help="ridge penalty")
    ap.add_argument("--encoder-norm", nargs="+", default=list(ENCODER_NORMS), choices=ENCODER_NORMS)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    pre = load_pretrained(args.checkpoint)
    category = pre.spec.category
    fit = index_split(args.data, category, "train").objects[: args.fit_objects]
    test = index_split(args.data, category, "test").objects[: args.test_objects]
    if not fit or not test:
        raise SystemExit(f"error: {args.data}: the probe needs {category}_train and {category}_test objects")
    results = {}
    print("| encoder norm | fit pixels | test pixels | R^2 red | R^2 green | R^2 blue | RMS error |\n"
          "|---|---:|---:|---:|---:|---:|---:|")
    for norm in args.encoder_norm:
        session = InferenceSession(pre, SessionOptions(inputs="dataset", data_root=args.data, records=fit + test,
                                                       encoder_norm=norm))
        plane, _ = session.dataset_symmetry(category)
        x, y, owner = object_pixels(session, fit + test, plane)
        on_fit = owner < len(fit)
        if on_fit.all() or not on_fit.any():
            raise SystemExit("error: no all-object feature pixel on the fit or the test objects")
        probe = ridge_probe(x[on_fit], y[on_fit], x[~on_fit], y[~on_fit], args.alpha)
        results[norm] = {**probe, "fit_pixels": int(on_fit.sum()), "test_pixels": int((~on_fit).sum())}
        r2 = probe["r2"]
        print(f"| {norm} | {on_fit.sum()} | {(~on_fit).sum()} | {r2[0]:.3f} | {r2[1]:.3f} | {r2[2]:.3f} | "
              f"{probe['rmse']:.4f} |")
    if args.json is not None:
        args.json.write_text(json.dumps({"checkpoint": args.checkpoint, "alpha": args.alpha, **results}, indent=1))


if __name__ == "__main__":
    main()
