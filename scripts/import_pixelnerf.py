"""Convert official pixelNeRF weights (sxyu/pixel-nerf) into a depthnerf checkpoint of the paper's baseline, so that
``depthnerf eval`` scores pixelNeRF's own models by the same evaluation as every other row of Table 1.

    python scripts/import_pixelnerf.py --weights checkpoints/srn_car/pixel_nerf_latest --category cars \\
        --out pixelnerf-srn-cars.safetensors
    depthnerf eval --checkpoint pixelnerf-srn-cars.safetensors --data data/srn --split test --out eval/pixelnerf-cars

The weights file is pixelNeRF's ``torch.save(net.state_dict())`` (its released ``pixel_nerf_weights.zip`` holds
one per experiment: ``srn_car/``, ``srn_chair/``, ...), read with ``weights_only=True``. The network is the
``paper-<category>`` preset's baseline (``--depth none``), which is pixelNeRF's SRN config; the conversion and why
it is exact: :mod:`depthnerf.pretrained.official_pixelnerf`. The checkpoint renders as the preset does (64 coarse
+ 16 importance + 16 depth-guided samples, the category's SRN near/far, pixelNeRF's pixel centres) and records
the source file's SHA-256. Written atomically in float32; nothing is downloaded.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from depthnerf.config_io import to_dict
from depthnerf.depth.prior import PriorConfig
from depthnerf.errors import DepthnerfError
from depthnerf.files import sha256_file
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.pretrained.official_pixelnerf import convert_official_state, read_official_state
from depthnerf.pretrained.spec import SPEC_KEY
from depthnerf.pretrained.weights import save_weights
from depthnerf.state_dicts import load_state_strict
from depthnerf.train.config import PRESETS, inference_spec, preset

IMPORTED_BY = "scripts/import_pixelnerf.py"
"""The ``imported_by`` metadata of every checkpoint this script writes."""


def import_pixelnerf(weights: Path, out: Path, category: str, preset_name: str | None = None) -> dict:
    """Write ``out`` (a depthnerf checkpoint) from the official pixelNeRF ``weights``; returns what it recorded."""
    name = preset_name or f"paper-{category}"
    cfg = preset(name)
    if cfg.data.category != category:
        raise DepthnerfError(f"--preset {name} is for {cfg.data.category}, not --category {category}")
    cfg.prior = PriorConfig(estimator="none")
    spec = inference_spec(cfg, framing="srn")
    state = convert_official_state(read_official_state(weights), spec.model, weights)
    model = PixelNeRF(spec.model, depth_aware=False)
    load_state_strict(model, state, weights, mismatch=f"the weights do not fit the {name} baseline network")
    source = {"file": Path(weights).name, "sha256": sha256_file(weights), "preset": name}
    out.parent.mkdir(parents=True, exist_ok=True)
    save_weights(out, model, to_dict(spec.model), step=0,
                 extra={SPEC_KEY: spec.to_json(), "imported_by": IMPORTED_BY,
                        "imported_from": json.dumps(source, sort_keys=True)})
    return {"out": str(out), **source}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("--weights", type=Path, required=True,
                        help="official pixelNeRF weights (e.g. checkpoints/srn_car/pixel_nerf_latest)")
    parser.add_argument("--category", required=True, choices=["cars", "chairs"],
                        help="the category the model was trained on (its near/far and camera defaults)")
    parser.add_argument("--out", type=Path, required=True, help="the depthnerf checkpoint to write (.safetensors)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None,
                        help="the network to load into (default: paper-CATEGORY, pixelNeRF's SRN config)")
    args = parser.parse_args(argv)
    try:
        record = import_pixelnerf(args.weights, args.out, args.category, args.preset)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {record['out']} from {args.weights} (sha256 {record['sha256'][:12]}..., the {record['preset']} "
          f"baseline); score it with: depthnerf eval --checkpoint {record['out']} --data DATA --split test "
          "--out OUT")
    return 0


if __name__ == "__main__":
    sys.exit(main())
