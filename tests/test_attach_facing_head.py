"""``scripts/attach_facing_head.py``: a facing head added to an exported checkpoint in place, the network left
byte for byte as it was, the cards updated (and updated again, not doubled, when a head is replaced)."""

from __future__ import annotations

import json

import pytest
import torch
from fixtures_scripts import load_script

from depthnerf.config_io import apply_overrides
from depthnerf.errors import DepthnerfError
from depthnerf.files import sha256_file
from depthnerf.model.facing_head import encoder_fingerprint, fit_ridge
from depthnerf.pretrained.load import load_pretrained
from depthnerf.pretrained.weights import read_weights, save_with_head
from tests.fixtures_checkpoints import tiny_config, tiny_model, tiny_run


def _head_file(source, path, median, encoder=None):
    """A weights file with a head fitted to a random linear angle on ``source``'s channels."""
    channels = source.model.encoder.latent_size
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(40, channels * 4, generator=gen, dtype=torch.float64)
    psi = torch.remainder(x[:, :3].sum(1) * 20.0, 180.0) - 90.0
    info = {"encoder": encoder or encoder_fingerprint(source.model), "lambda": 10.0, "views": 40, "objects": 10,
            "data": "d/cars_train", "validation_median_deg": median, "validation_p90_deg": 4.0}
    save_with_head(source.path, fit_ridge(x, psi, 10.0, channels, 2, info), path)
    return path


@pytest.fixture()
def shipped(tmp_path):
    """An exported mirror checkpoint (no head) in ``tmp_path/ship``: ``(exporter, attacher, export result)``."""
    exporter, attacher = load_script("export_checkpoint"), load_script("attach_facing_head")
    cfg = apply_overrides(tiny_config("cars", "none"), ["--model.mirror", "true"])
    res = exporter.export(tiny_run(tmp_path / "run", cfg), "cpu-cars-mirror", tmp_path / "ship")
    return exporter, attacher, res


def test_attach_keeps_the_network_and_updates_both_cards(shipped, tmp_path, monkeypatch, capsys):
    _, attacher, res = shipped
    before_tensors, before_meta = read_weights(res.weights)
    before_md = res.card_md.read_text()
    source = load_pretrained(res.weights)
    head = _head_file(source, tmp_path / "head.safetensors", 1.5)
    card = attacher.attach("cpu-cars-mirror", head, "depthnerf fit-facing --checkpoint cpu-cars-mirror --out HEAD",
                           tmp_path / "ship")

    loaded = load_pretrained(res.weights)
    assert loaded.facing_head is not None and loaded.facing_head.info["validation_median_deg"] == 1.5
    after_tensors, after_meta = read_weights(res.weights)
    for key, value in before_tensors.items():
        assert after_tensors[key].dtype == value.dtype and torch.equal(after_tensors[key], value), key
    assert {k: v for k, v in after_meta.items() if k != "facing_head"} == before_meta

    on_disk = json.loads(res.card_json.read_text())
    assert on_disk == card and card["sha256"] == sha256_file(res.weights)
    assert card["size_bytes"] == res.weights.stat().st_size and card["facing_head"]["attached"] is True
    md = res.card_md.read_text()
    assert md.count("| sha256 |") == 1 and f"`{card['sha256']}`" in md and f"{card['size_bytes']:,} bytes" in md
    assert "## Facing head" in md and "added to the exported file afterwards" in md
    assert md.index("## Facing head") < md.index("## Reproduce")
    lines = md.split("\n")
    at = next(i for i, line in enumerate(lines) if line.startswith("python scripts/export_checkpoint.py"))
    assert lines[at + 1].startswith("depthnerf fit-facing --checkpoint cpu-cars-mirror --out HEAD")
    assert lines[at + 2] == "python scripts/attach_facing_head.py --name cpu-cars-mirror --facing-head HEAD"
    assert md.replace("## Facing head", "").count("## ") == before_md.count("## ")

    from depthnerf.cli import main as cli_main
    from depthnerf.pretrained import load as pretrained

    monkeypatch.setattr(pretrained, "SHIPPED_DIR", tmp_path / "ship")
    assert cli_main(["checkpoints"]) == 0
    assert "; a facing head (--facing auto reads the plane from the photo)" in capsys.readouterr().out

    again = attacher.attach("cpu-cars-mirror", _head_file(source, tmp_path / "head2.safetensors", 2.25),
                            None, tmp_path / "ship")
    md2 = res.card_md.read_text()
    assert md2.count("## Facing head") == 1 and "median angle error 2.25 degrees" in md2 and "1.50" not in md2
    assert md2.count("python scripts/attach_facing_head.py") == 1 and md2.count("# HEAD: the facing head") == 1
    assert again["sha256"] == sha256_file(res.weights) != card["sha256"]


def test_refusals_leave_the_shipped_files_as_they_were(shipped, tmp_path, capsys):
    _, attacher, res = shipped
    source = load_pretrained(res.weights)
    ship = tmp_path / "ship"
    files = {p: p.read_bytes() for p in (res.weights, res.card_json, res.card_md)}
    other = tiny_model(apply_overrides(tiny_config("cars", "none"), ["--model.mirror", "true"]), seed=9)
    wrong = _head_file(source, tmp_path / "wrong.safetensors", 1.0, encoder=encoder_fingerprint(other))
    with pytest.raises(DepthnerfError, match="wrong.safetensors: its facing head was fitted on another encoder"):
        attacher.attach("cpu-cars-mirror", wrong, None, ship)
    with pytest.raises(DepthnerfError, match="carries no facing head"):
        attacher.attach("cpu-cars-mirror", res.weights, None, ship)
    assert attacher.main(["--name", "cpu-cars-nothing", "--facing-head", str(wrong), "--out", str(ship)]) == 2
    assert "cpu-cars-nothing.safetensors: not found" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in files} == files
    assert not list(ship.glob(".*attach*"))

    card = json.loads(res.card_json.read_text())
    res.card_json.write_text(json.dumps({**card, "sha256": "0" * 64}))
    with pytest.raises(DepthnerfError, match="cpu-cars-mirror.json: its sha256 is not that of"):
        attacher.attach("cpu-cars-mirror", _head_file(source, tmp_path / "h.safetensors", 1.0), None, ship)
