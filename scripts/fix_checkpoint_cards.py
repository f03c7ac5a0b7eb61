"""Rewrite exported checkpoint cards (``<name>.json`` + ``<name>.md``) with portable paths and their data framing.

``python scripts/fix_checkpoint_cards.py depthnerf/checkpoints/cpu-*.json --framing legacy --relative-to DIR``

Absolute paths in the cards become relative to ``--relative-to`` (default: the repository), the home directory
in eval messages becomes ``~`` (:func:`export_checkpoint.portable_path` / ``portable_text``, what
``scripts/export_checkpoint.py`` now writes), and ``--framing`` records the training data's framing
(``framing``, plus ``generator`` read from the model card) and ``--framing F`` in the card's ``depthnerf synth``
command. The ``.safetensors`` weights are only read (for ``data.pixel_center``), never written.

``--total-steps N`` (one card) records the steps behind a warm-started model in all, for a chain of warm starts
exported before cards counted them (``total_steps``; the steps behind its source become ``N`` minus its own), and
rewrites the card's "training steps" row; take ``N`` from the chain of commands in docs/RESULTS.md.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from checkpoint_card import training_steps  # noqa: E402
from export_checkpoint import REPO_ROOT, portable_path, portable_text  # noqa: E402

from depthnerf.data.synth.framing import FRAMINGS, get_framing  # noqa: E402
from depthnerf.errors import DepthnerfError  # noqa: E402
from depthnerf.files import read_json_object, write_text_atomic  # noqa: E402
from depthnerf.train import checkpoint as ckpt  # noqa: E402


def fix_card(card_json: Path, framing: str | None = None, base: Path = REPO_ROOT,
             total_steps: int | None = None) -> dict:
    """Rewrite an exported card pair (``card_json`` and the ``.md`` beside it) with portable paths (module
    docstring), given ``framing`` the training data's framing, and given ``total_steps`` a warm-start chain's
    steps in all; the weights are not touched."""
    card_json, card_md = Path(card_json), Path(card_json).with_suffix(".md")
    card = read_json_object(card_json, "checkpoint card")
    md = card_md.read_text() if card_md.is_file() else None
    renames: dict[str, str] = {}

    def _fix(section: dict, key: str, fn) -> None:
        old = section.get(key)
        if isinstance(old, str):
            new = fn(old, base)
            section[key] = new
            if new != old:
                renames[old] = new

    for key in ("data_root", "run_path"):
        _fix(card, key, portable_path)
    ev = card.get("evaluation")
    if isinstance(ev, dict):
        for key in ("summary", "data_root"):
            _fix(ev, key, portable_path)
        for key in ("lpips_status", "mesh_status"):
            _fix(ev, key, portable_text)
    if framing is not None:
        card["framing"] = get_framing(framing).name
        found = re.search(r"generator `([^`]+)`", md or "")
        if "generator" not in card and found:
            card["generator"] = found.group(1)
    weights = card_json.with_suffix(".safetensors")
    if "pixel_center" not in card and weights.is_file():
        _, meta = ckpt.read_weights(weights)
        card["pixel_center"] = float(json.loads(meta["train_config"]).get("data", {}).get("pixel_center", 0.0))
    if total_steps is not None:
        warm = card.get("init_from")
        if not warm or total_steps <= card["step"]:
            raise DepthnerfError(f"{card_json}: --total-steps {total_steps} is for a warm-started model with more "
                                 f"steps than its own {card['step']}")
        card["total_steps"], warm["total_steps"] = total_steps, total_steps - card["step"]
    write_text_atomic(card_json, json.dumps(card, indent=1) + "\n")
    if md is not None:
        for old, new in sorted(renames.items(), key=lambda kv: -len(kv[0])):
            md = md.replace(old, new)
        if framing is not None and "framing `" not in md:
            md = re.sub(r"(generator `[^`]+`), ", rf"\1, framing `{card['framing']}` (docs/data.md), pixel centres "
                        rf"read as `data.pixel_center` {card.get('pixel_center', 0.0)}, ", md, count=1)
            md = "\n".join(line + f" --framing {card['framing']}" if line.startswith("depthnerf synth ")
                           and "--framing" not in line else line for line in md.split("\n"))
        if total_steps is not None:
            md = re.sub(r"^\| training steps \|.*$", f"| training steps | {training_steps(card)} |", md, count=1,
                        flags=re.M)
        write_text_atomic(card_md, md)
    return card


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("cards", type=Path, nargs="+", help="card .json files (the .md beside each is rewritten too)")
    p.add_argument("--framing", choices=sorted(FRAMINGS), help="framing of the data the checkpoints were trained on")
    p.add_argument("--relative-to", type=Path, default=REPO_ROOT,
                   help=f"base of the relative paths (default the repository, {REPO_ROOT})")
    p.add_argument("--total-steps", type=int, help="a warm-started model's training steps in all (one card)")
    args = p.parse_args(argv)
    if args.total_steps is not None and len(args.cards) != 1:
        p.error("--total-steps is for one card")
    try:
        for path in args.cards:
            fix_card(path, args.framing, args.relative_to, args.total_steps)
            print(f"rewrote {path} and {path.with_suffix('.md')}")
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
