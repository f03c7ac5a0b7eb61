"""Print the synthetic-benchmark framing a checkpoint was trained on (``srn`` or ``legacy``), read from its card.

Used by the shell scripts that synthesise test objects for a checkpoint (``generalisation_check.sh``,
``pixel_center_cost.sh``) as their default ``FRAMING``:

    python scripts/checkpoint_framing.py cpu-cars-depth        # a shipped name, weights file or run folder
"""

from __future__ import annotations

import sys

from depthnerf.data.synth.framing import checkpoint_framing
from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.load import resolve_checkpoint


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__.strip().splitlines()[0], file=sys.stderr)
        return 2
    try:  # without a data root the category is not consulted: the checkpoint card, else the default framing
        print(checkpoint_framing(resolve_checkpoint(sys.argv[1]), None, "")[0])
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
