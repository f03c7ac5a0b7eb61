"""Print the synthetic-benchmark framing a checkpoint was trained on (``srn`` or ``legacy``): its inference spec's
(``InferenceSpec.framing``; derived at load for checkpoints written before the spec held it).

Used by the shell scripts that synthesise test objects for a checkpoint (``generalisation_check.sh``,
``pixel_center_cost.sh``) as their default ``FRAMING``:

    python scripts/checkpoint_framing.py cpu-cars-depth        # a shipped name, weights file or run folder
"""

from __future__ import annotations

import sys

from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.load import load_pretrained


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__.strip().splitlines()[0], file=sys.stderr)
        return 2
    try:
        print(load_pretrained(sys.argv[1]).spec.framing)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
