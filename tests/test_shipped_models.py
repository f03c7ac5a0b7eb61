"""The shipped models as a set: the repository that carries them stays small enough to travel to a lent GPU machine
(docs/speed.md, "Measuring on a lent GPU": the working tree that travels is capped at 64 MiB, and the wheels
archive and a run's files need room beside it), every checkpoint that stopped shipping keeps a card that says what
replaced it, and the demo and the app default to the best shipped model of each category."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from fixtures_scripts import load_script

from depthnerf.pretrained.load import retired_checkpoints, shipped_checkpoints
from depthnerf.pretrained.recommended import RECOMMENDED

ROOT = Path(__file__).resolve().parent.parent
HEADROOM = 4_000_000
"""Kept free under the travel limit (``scripts/travel_size.py``) for the carried wheels archive (``.whl``, about
1 MB) and a run's untracked files."""


def _travel():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    return load_script("travel_size")


def test_tracked_files_leave_room_under_the_gpu_travel_limit():
    travel = _travel()
    sizes = {p: p.stat().st_size for p in travel.git_files(ROOT)}
    total, budget = sum(sizes.values()), travel.LIMIT_BYTES - HEADROOM
    largest = ", ".join(f"{p.relative_to(ROOT)} {s / 1e6:.1f} MB"
                        for p, s in sorted(sizes.items(), key=lambda kv: -kv[1])[:3])
    assert total <= budget, f"tracked files hold {total / 1e6:.1f} MB, over the {budget / 1e6:.0f} MB budget " \
                            f"(largest: {largest})"


def test_travel_size_sums_what_a_call_sends(tmp_path, capsys, monkeypatch):
    """Tracked, untracked-not-ignored and carried files count; ignored ones that are not carried do not; over the
    limit is exit 1, a missing carried path an error."""
    travel = _travel()
    repo = tmp_path / "repo"
    repo.mkdir()
    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    (repo / ".gitignore").write_text("runs/\n.whl/\n")
    (repo / "tracked.bin").write_bytes(b"t" * 1000)
    subprocess.run(["git", "add", "."], cwd=repo, check=True)
    (repo / "new.txt").write_bytes(b"u" * 300)
    (repo / "runs").mkdir()
    (repo / "runs" / "big.bin").write_bytes(b"r" * 50_000)
    (repo / ".whl" / "site").mkdir(parents=True)
    (repo / ".whl" / "site" / "a.tar").write_bytes(b"w" * 200)
    parts = travel.travel_parts(repo, [".whl"])
    names = {k: sorted(p.name for p in v) for k, v in parts.items()}
    assert names == {"tracked": [".gitignore", "tracked.bin"], "untracked, not ignored": ["new.txt"],
                     "carried": ["a.tar"]}
    assert travel.main(["--root", str(repo), ".whl"]) == 0
    monkeypatch.setattr(travel, "LIMIT_BYTES", 1000)
    assert travel.main(["--root", str(repo), ".whl"]) == 1
    assert "would be REFUSED" in capsys.readouterr().out
    with pytest.raises(SystemExit, match="no-such: a carried path that does not exist"):
        travel.main(["--root", str(repo), "no-such"])


def test_retired_checkpoints_keep_cards_naming_a_shipped_replacement():
    retired, shipped = retired_checkpoints(), shipped_checkpoints()
    assert retired, "no retired cards found: package data or the retired folder moved"
    for name, card in retired.items():
        assert name not in shipped
        assert card.with_suffix(".json").is_file()
        note = card.read_text().split("\n\n")[1]
        assert note.startswith("> **Retired: the weights no longer ship.**")
        replacements = set(re.findall(r"`(cpu-[a-z0-9-]+)`", note)) - {name}
        assert replacements and replacements <= set(shipped), f"{card}: names no shipped replacement"
        assert f'RUNS="{name.split("-")[1]}-bundled-sym"' in note  # the rebuild command


def _card(path: Path) -> dict:
    return json.loads(path.with_suffix(".json").read_text())


def test_demo_and_app_default_to_the_best_shipped_model_per_category():
    from depthnerf.app.logic import SHIPPED_MODELS
    from depthnerf.demo import DEFAULT_CHECKPOINTS

    shipped = shipped_checkpoints()
    assert set(DEFAULT_CHECKPOINTS.values()) == set(SHIPPED_MODELS.values()) == set(RECOMMENDED.values())
    for category, name in RECOMMENDED.items():
        best = _card(shipped[name])
        assert best["category"] == category
        rivals = {other: _card(path) for other, path in shipped.items() if other != name}
        same = {other: card["metrics"]["psnr"] for other, card in rivals.items()
                if card["category"] == category and card.get("protocol") == best["protocol"] and card["metrics"]}
        assert same, f"no other {category} model evaluated on {name}'s protocol to rank it against"
        assert best["metrics"]["psnr"] > max(same.values()), f"{name} is not the best shipped {category} model: {same}"


def test_readme_table_of_the_shipped_checkpoints_agrees_with_their_cards():
    """README's table of the shipped checkpoints prints each model's card metrics (to the digits it shows), so a
    re-export cannot leave the front page quoting the model it replaced."""
    shipped = shipped_checkpoints()
    rows = [line for line in (ROOT / "README.md").read_text().splitlines() if line.startswith("| `cpu-*-")]
    assert len(rows) == 3, rows
    keys = ("psnr", "ssim", "chamfer_l1", "fscore")
    checked = 0
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        pattern = cells[0].strip("`")
        printed = {"cars": cells[2:6], "chairs": cells[7:11]}
        for category, values in printed.items():
            name = pattern.replace("*", category)
            assert name in shipped, f"README names {name}, which does not ship"
            metrics = _card(shipped[name])["metrics"]
            for key, text in zip(keys, values, strict=True):
                text = text.strip("*")
                digits = len(text.split(".")[1])
                assert f"{metrics[key]:.{digits}f}" == text, f"README: {name} {key} {text}, its card {metrics[key]}"
                checked += 1
    assert checked == 24


def test_each_card_names_its_weights_file_by_size_and_sha256():
    """A shipped file rewritten without its cards (a re-export half done, a head attached by hand) shows here."""
    from depthnerf.files import sha256_file

    for name, path in shipped_checkpoints().items():
        card = _card(path)
        assert card["sha256"] == sha256_file(path), f"{name}.json: sha256 is not that of {path.name}"
        assert card["size_bytes"] == path.stat().st_size, f"{name}.json: size_bytes is not {path.name}'s"
        assert f"`{card['sha256']}`" in path.with_suffix(".md").read_text(), f"{name}.md: another sha256"


def test_the_shipped_mirror_models_carry_facing_heads_of_their_own_encoders():
    """``--facing auto`` and the app's ticked box rely on it; the head is checked against the encoder on load."""
    from depthnerf.pretrained.load import load_pretrained

    for name in ("cpu-cars-sym-pp", "cpu-chairs-sym-pp"):
        path = shipped_checkpoints()[name]
        head = load_pretrained(path).facing_head
        assert head is not None, f"{name}: no facing head"
        assert _card(path)["facing_head"]["validation_median_deg"] == head.info["validation_median_deg"]
