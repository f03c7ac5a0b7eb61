"""Add a facing head to an exported checkpoint, in place, with its cards.

``python scripts/attach_facing_head.py --name cpu-cars-sym-pp --facing-head HEAD.safetensors
[--facing-command "the fit-facing command"] [--out depthnerf/checkpoints] [--relative-to DIR]``

For a checkpoint exported before its facing head was fitted (``scripts/export_checkpoint.py --facing-head`` does
both at once, but needs the run folder). ``HEAD.safetensors`` is a file written by ``depthnerf fit-facing``; its head
must have been fitted on this checkpoint's encoder (:func:`depthnerf.model.facing_head.check_encoder`). The weights
file is rewritten with the head (:func:`depthnerf.pretrained.weights.save_with_head`; a head it had is replaced),
and before it takes the shipped name every network tensor and every metadata entry but the head's is checked to be
unchanged, byte for byte: the card's evaluation, fp16 check and provenance still describe the file. Then
``<name>.json`` gets the new ``sha256``, ``size_bytes`` and a ``facing_head`` entry (the head's description, the
``--facing-command`` and ``attached: true``), and ``<name>.md`` the new weights rows, the "Facing head" section and,
after the export line of "Reproduce", the fit and attach lines.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the sibling scripts, however this runs
from checkpoint_card import attach_line, facing_fit_line, facing_head_lines, file_rows  # noqa: E402
from export_checkpoint import REPO_ROOT, add_card_arguments, portable_text, read_facing_head  # noqa: E402

from depthnerf.errors import DepthnerfError  # noqa: E402
from depthnerf.files import read_json_object, sha256_file, write_text_atomic  # noqa: E402
from depthnerf.model.facing_head import META_KEY as HEAD_META_KEY  # noqa: E402
from depthnerf.model.facing_head import PREFIX as HEAD_PREFIX  # noqa: E402
from depthnerf.pretrained.load import SHIPPED_DIR, load_pretrained  # noqa: E402
from depthnerf.pretrained.weights import read_weights, save_with_head  # noqa: E402

FIT_MARK = "# HEAD: the facing head's file"
"""How a fit line of a card's "Reproduce" ends (:func:`checkpoint_card.facing_fit_line`)."""


def check_network_unchanged(before: Path, after: Path) -> None:
    """Raise unless ``after`` holds ``before``'s network tensors and metadata exactly (heads aside)."""
    t0, m0 = read_weights(before)
    t1, m1 = read_weights(after)
    net0 = {k: v for k, v in t0.items() if not k.startswith(HEAD_PREFIX)}
    net1 = {k: v for k, v in t1.items() if not k.startswith(HEAD_PREFIX)}
    changed = sorted(set(net0) ^ set(net1)) or [k for k in net0 if net0[k].dtype != net1[k].dtype
                                                    or not torch.equal(net0[k], net1[k])]
    meta0 = {k: v for k, v in m0.items() if k != HEAD_META_KEY}
    meta1 = {k: v for k, v in m1.items() if k != HEAD_META_KEY}
    changed += sorted(k for k in set(meta0) | set(meta1) if meta0.get(k) != meta1.get(k))
    if changed:
        raise DepthnerfError(f"{after}: writing the head changed the network ({', '.join(changed[:3])}); not attached")


def card_markdown(md: str, card: dict, path: Path) -> str:
    """``md`` (a model card) with ``card``'s weights rows, its "Facing head" section and its fit and attach lines
    (any earlier ones replaced)."""
    rows = file_rows(card)
    for key, row in (("weights", rows[0]), ("sha256", rows[1])):
        md, n = re.subn(rf"^\| {key} \|.*$", lambda _m, r=row: r, md, count=1, flags=re.M)
        if n != 1:
            raise DepthnerfError(f"{path}: no '| {key} |' row in the card's table; rewrite the card by exporting")
    md = re.sub(r"\n## Facing head\n.*?(?=\n## )", "", md, flags=re.S)
    if "\n## Reproduce\n" not in md:
        raise DepthnerfError(f"{path}: no '## Reproduce' section; rewrite the card by exporting")
    md = md.replace("\n## Reproduce\n", "\n" + "\n".join(facing_head_lines(card["facing_head"])) + "\n\n## Reproduce\n",
                    1)
    lines = [line for line in md.split("\n") if not line.endswith(FIT_MARK)
             and not line.startswith("python scripts/attach_facing_head.py")]
    export = [i for i, line in enumerate(lines) if line.startswith("python scripts/export_checkpoint.py")]
    if len(export) != 1:
        raise DepthnerfError(f"{path}: expected one export line in 'Reproduce', found {len(export)}")
    at = export[0] + 1
    lines[at:at] = [facing_fit_line(card["facing_head"], card["category"]), attach_line(card["name"])]
    return "\n".join(lines)


def attach(name: str, head_path: Path, facing_command: str | None = None, out: Path = SHIPPED_DIR,
           base: Path = REPO_ROOT) -> dict:
    """Attach the head of ``head_path`` to ``out/<name>.safetensors`` and update its cards (module docstring);
    returns the new card."""
    weights, card_json, card_md = (out / f"{name}{ext}" for ext in (".safetensors", ".json", ".md"))
    for path in (weights, card_json, card_md):
        if not path.is_file():
            raise DepthnerfError(f"{path}: not found (attach to an exported checkpoint: --name and --out)")
    card = read_json_object(card_json, "checkpoint card")
    if card.get("sha256") != sha256_file(weights):
        raise DepthnerfError(f"{card_json}: its sha256 is not that of {weights.name} (the cards are stale)")
    source = load_pretrained(weights)
    head = read_facing_head(Path(head_path), source)
    staged = out / f".{name}.attach.safetensors"
    try:
        save_with_head(weights, head, staged)
        check_network_unchanged(weights, staged)
        card = {**card, "sha256": sha256_file(staged), "size_bytes": staged.stat().st_size,
                "facing_head": {**head.describe(), "command": portable_text(facing_command, base), "attached": True}}
        md = card_markdown(card_md.read_text(), card, card_md)
    except BaseException:
        staged.unlink(missing_ok=True)
        raise
    os.chmod(staged, 0o644)
    os.replace(staged, weights)
    write_text_atomic(card_json, json.dumps(card, indent=1) + "\n")
    write_text_atomic(card_md, md)
    return card


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--name", required=True, help="the exported checkpoint, e.g. cpu-cars-sym-pp")
    p.add_argument("--facing-head", type=Path, required=True, help="a weights file from 'depthnerf fit-facing'")
    p.add_argument("--out", type=Path, default=SHIPPED_DIR, help=f"folder of the checkpoint (default {SHIPPED_DIR})")
    add_card_arguments(p)
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        with torch.no_grad():
            card = attach(args.name, args.facing_head, args.facing_command, args.out, args.relative_to)
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    fh = card["facing_head"]
    print(f"attached a facing head to {card['name']} ({fh['views']} views of {fh['objects']} objects, held-out "
          f"median {fh['validation_median_deg']:.2f} deg); {card['size_bytes']:,} bytes, sha256 {card['sha256'][:12]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
