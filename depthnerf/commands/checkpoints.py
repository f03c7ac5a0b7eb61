"""``depthnerf checkpoints``: list the checkpoints shipped inside the package, with their model-card summary.

A shipped checkpoint is ``depthnerf/checkpoints/<name>.safetensors`` (written by training or
``scripts/export_checkpoint.py``); ``--checkpoint <name>`` then works in ``eval`` and ``reconstruct``. Shown per
checkpoint: name, preset, category, depth prior, training steps (all from the weights' metadata; the card adds a
warm start's steps before them), whether it carries a facing head (:mod:`depthnerf.model.facing_head`), and
metrics when
recorded: the metadata key ``metrics`` (a JSON object) or a model card ``<name>.json`` next to the weights with a
``metrics`` object (keys such as ``psnr``, ``ssim``, plus free text under ``protocol``; ``null`` = not evaluated,
as ``scripts/export_checkpoint.py`` writes it without ``--eval-summary``). A ``<name>.md`` model card
is pointed to. Retired checkpoints (cards kept in ``depthnerf/checkpoints/retired/``, weights no longer shipped) are
named on a last line of the text listing. Nothing is downloaded; with no checkpoint shipped the command says so and exits 0.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.card import total_steps, warm_start_steps


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print the list as JSON")


def _json_field(text: str | None, where: str) -> dict:
    if text is None:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        raise DepthnerfError(f"{where}: not valid JSON") from None
    if not isinstance(value, dict):
        raise DepthnerfError(f"{where}: expected a JSON object")
    return value


def _depth_weights(meta: dict[str, str], where: str) -> str | None:
    """The depth weights the checkpoint reads: a shipped net's name, else the file or hub id as recorded (None: no
    prior, or no spec to say)."""
    from depthnerf.depth.prior import portable_prior
    from depthnerf.pretrained.spec import SPEC_KEY, spec_from_json

    if SPEC_KEY not in meta:
        return None
    spec = spec_from_json(meta[SPEC_KEY], where)
    return portable_prior(spec.prior, spec.prior_weights_hash).checkpoint if spec.depth_aware else None


def describe(name: str, path: Path) -> dict:
    """The model-card summary of one shipped checkpoint (metadata only, the weights are not loaded)."""
    from safetensors import SafetensorError, safe_open

    from depthnerf.model.facing_head import META_KEY as HEAD_META_KEY

    try:
        with safe_open(str(path), framework="pt") as f:
            meta = dict(f.metadata() or {})
    except (SafetensorError, OSError) as err:
        raise DepthnerfError(f"{path}: unreadable shipped checkpoint ({err})") from None
    train = _json_field(meta.get("train_config"), f"{path} metadata 'train_config'")
    metrics = _json_field(meta.get("metrics"), f"{path} metadata 'metrics'")
    card_json, card_md = path.with_suffix(".json"), path.with_suffix(".md")
    card: dict = {}
    if card_json.is_file():
        card = _json_field(card_json.read_text(), str(card_json))
        card_metrics = card.get("metrics") or {}  # null = exported without an evaluation
        if not isinstance(card_metrics, dict):
            raise DepthnerfError(f"{card_json}: 'metrics' must be a JSON object or null")
        metrics = {**metrics, **card_metrics}
    steps, protocol, warm_steps = int(meta.get("step", 0)), card.get("protocol"), warm_start_steps(card)
    total = total_steps({"total_steps": meta.get("total_steps"), **card}, steps)  # the card's count wins
    return {"name": name, "path": str(path), "preset": train.get("preset", "unknown"),
            "depth_weights": _depth_weights(meta, str(path)),
            "category": train.get("data", {}).get("category", "unknown"),
            "depth_prior": train.get("prior", {}).get("estimator", "unknown"), "steps": steps,
            "warm_start_steps": warm_steps, "total_steps": total, "metrics": metrics or None, "protocol": protocol,
            "facing_head": HEAD_META_KEY in meta,
            "model_card": str(card_md) if card_md.is_file() else (str(card_json) if card_json.is_file() else None)}


def run(args: argparse.Namespace) -> int:
    from depthnerf.pretrained import load as pretrained

    shipped = pretrained.shipped_checkpoints()
    rows = [describe(name, path) for name, path in shipped.items()]
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    if not rows:
        print(f"no checkpoints are shipped with this version of depthnerf ({pretrained.SHIPPED_DIR} holds no "
              "*.safetensors). Train one with 'depthnerf train' and pass its run folder or a weights file to "
              "--checkpoint.")
    for r in rows:
        metrics = ", ".join(f"{k} {v:.4g}" if isinstance(v, int | float) else f"{k} {v}"
                            for k, v in (r["metrics"] or {}).items()) or "no metrics recorded"
        print(f"{r['name']}: preset {r['preset']}, category {r['category']}, depth prior {r['depth_prior']}"
              + (f" ({Path(r['depth_weights']).name} weights)" if r.get("depth_weights") else "") + ", "
              f"{r['steps']} steps"
              + (f" after a {r['warm_start_steps']}-step warm start ({r['total_steps']} in all)"
                 if r["warm_start_steps"] else "")
              + f"; {metrics}" + (f" ({r['protocol']})" if r["protocol"] else "")
              + ("; a facing head (--facing auto reads the plane from the photo)" if r["facing_head"] else "")
              + (f"; card {r['model_card']}" if r["model_card"] else ""))
    retired = pretrained.retired_checkpoints()
    if retired:
        cards = pretrained.SHIPPED_DIR / "retired"
        print(f"retired (weights no longer shipped; cards in {cards}): {', '.join(retired)}")
    return 0
