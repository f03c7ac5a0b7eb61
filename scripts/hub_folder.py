"""Lay out a checkpoint as a Hugging Face model repository, ready for ``hf upload OWNER/REPO OUT .``.

    python scripts/hub_folder.py CHECKPOINT OUT [--card CARD.md] [--license mit]

CHECKPOINT is anything ``--checkpoint`` accepts (a shipped name, a weights file, a checkpoint or run folder). OUT
gets ``model.safetensors`` (the weights file, byte for byte: what ``hf://OWNER/REPO`` loads) and ``README.md``, the
repository's model card: Hugging Face's YAML header (library, licence, tags, the category and depth prior) above
the checkpoint's own card (``--card``; default: the ``.md`` beside the weights, as ``scripts/export_checkpoint.py``
and the shipped checkpoints have) or, without one, a short card stating what the checkpoint's spec says. The
weights are loaded first, strictly, so a damaged or mismatched file never reaches OUT. Nothing is uploaded.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.hub import HUB_DEFAULT_FILE
from depthnerf.pretrained.load import load_pretrained


def header(category: str, prior: str, licence: str) -> str:
    """The model card's YAML header (the Hub reads library, licence and tags from it)."""
    tags = ["depthnerf", "pixelnerf", "nerf", "single-image-3d-reconstruction", category,
            "depth-aware" if prior != "none" else "baseline"]
    return "\n".join(["---", "library_name: depthnerf", f"license: {licence}", "tags:",
                      *[f"- {t}" for t in tags], "---", ""])


def default_card(name: str, spec, step: int) -> str:
    """A card from the checkpoint's inference spec alone, for weights without a card of their own."""
    return (f"# {name}\n\ndepthnerf checkpoint: category `{spec.category}`, depth prior `{spec.prior.estimator}`, "
            f"{spec.resolution} px, {step} training steps.\n\n```python\nfrom depthnerf import Reconstructor\n"
            f"rec = Reconstructor.from_pretrained(\"hf://OWNER/REPO\")\n```\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("checkpoint", help="shipped name, weights file, checkpoint or run folder")
    parser.add_argument("out", type=Path, help="folder to write (must not exist yet)")
    parser.add_argument("--card", type=Path, help="model card to put under the header (default: NAME.md beside "
                                                  "the weights, if any)")
    parser.add_argument("--license", default="mit", help="licence in the header (default mit, this repository's)")
    args = parser.parse_args(argv)
    try:
        pre = load_pretrained(args.checkpoint)
        if args.out.exists():
            raise DepthnerfError(f"{args.out}: already exists; give a new folder")
        card_path = args.card or pre.path.with_suffix(".md")
        if args.card is not None and not args.card.is_file():
            raise DepthnerfError(f"{args.card}: no such model card")
        card = card_path.read_text() if card_path.is_file() else default_card(pre.path.stem, pre.spec, pre.step)
        args.out.mkdir(parents=True)
        shutil.copyfile(pre.path, args.out / HUB_DEFAULT_FILE)
        (args.out / "README.md").write_text(header(pre.spec.category, pre.spec.prior.estimator, args.license)
                                            + "\n" + card)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}/{HUB_DEFAULT_FILE} (sha256 {pre.sha256[:12]}) and {args.out}/README.md; upload with: "
          f"hf upload OWNER/REPO {args.out} .")
    return 0


if __name__ == "__main__":
    sys.exit(main())
