"""``scripts/export_checkpoint.py``: which checkpoint is exported, fp16 conversion, round trip, cards, listing.

Runs are tiny random models written by the training checkpoint writer (``fixtures_checkpoints.tiny_run``):
``best`` (step 5) and the latest (step 10) hold different weights, so picking the wrong one shows.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
from pathlib import Path

import pytest
import torch
from fixtures_checkpoints import tiny_bundled, tiny_config, tiny_run
from fixtures_scripts import load_script
from safetensors import safe_open

from depthnerf.cli import main as cli_main
from depthnerf.commands.checkpoints import describe
from depthnerf.files import sha256_file
from depthnerf.model.pixelnerf import SourceViews
from depthnerf.pretrained import load as pretrained
from depthnerf.pretrained.load import load_pretrained
from depthnerf.train import checkpoint as ckpt

PROTOCOL = "SRN protocol: input view 64, targets = all other 250 views with stride 25 (10 views), 2 of 2 objects"


def _script():
    return load_script("export_checkpoint")


@pytest.fixture(scope="module")
def exporter():
    return _script()


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("export")
    weights = tiny_bundled(tmp / "bundled.safetensors")
    return tiny_run(tmp / "cpu-cars-depth-run", tiny_config("cars", "bundled", weights))


def _summary(path: Path, sha: str, **changes) -> Path:
    data = {"psnr": 23.4567, "ssim": 0.91234, "lpips": None, "chamfer_l1": 0.0456, "fscore": 0.5,
            "fscore_tau": 0.01, "objects": 2, "views": 20, "checkpoint_sha256": sha, "preset": "cpu-cars",
            "category": "cars", "depth_prior": "bundled", "method": "depth-aware (bundled)", "protocol": PROTOCOL,
            "split": "test", "views_stride": 25, "max_objects": 2, "resolution": 16, "input_resolution": 16,
            "metrics_path": "float renders (eval.py)", "lpips_status": "unavailable: test",
            "aggregation": "mean over objects", "data_card": {"root": "/data/synth"}, **changes}
    path.write_text(json.dumps(data))
    return path


def test_exports_best_as_fp16_with_metadata(exporter, run, tmp_path):
    best = run / "checkpoints" / "best" / "model.safetensors"
    res = exporter.export(run, "cpu-cars-depth", tmp_path, command="depthnerf train --preset cpu-cars --x 1")
    src_tensors, src_meta = ckpt.read_weights(best)
    tensors, meta = ckpt.read_weights(res.weights)
    assert set(tensors) == set(src_tensors)
    changed = 0
    for key, value in tensors.items():
        ref = src_tensors[key]
        if ref.is_floating_point():
            assert value.dtype == torch.float16, key
            # fp16 rounding: relative error <= 2^-11 (plus the subnormal step near zero)
            assert torch.all((value.float() - ref).abs() <= ref.abs() * 2.0**-11 + 2.0**-24), key
            changed += int(not torch.equal(value.float(), ref))
        else:
            assert value.dtype == ref.dtype and torch.equal(value, ref), key
    assert changed > 0
    assert int(tensors["encoder.trunk.bn1.num_batches_tracked"]) == 1234
    for key in ("format", "config", "train_config", "step"):
        assert meta[key] == src_meta[key], key
    assert meta["step"] == "5"  # best, not the latest (step 10)
    assert meta["source_sha256"] == sha256_file(best) and meta["source_run"] == run.name
    assert meta["source_file"] == "checkpoints/best/model.safetensors" and meta["dtype"] == "float16"
    assert res.weights.stat().st_size < 0.6 * best.stat().st_size
    assert not list(tmp_path.glob(".*"))  # no staged file left
    assert res.weights.stat().st_mode & 0o777 == 0o644


def test_roundtrip_within_fp16_tolerance(exporter, run, tmp_path):
    res = exporter.export(run, "cpu-cars-depth", tmp_path)
    src, out = load_pretrained(run), load_pretrained(res.weights)
    assert src.step == out.step == 5
    assert all(v.dtype == torch.float32 for v in out.model.state_dict().values() if v.is_floating_point())
    torch.manual_seed(0)
    sources = SourceViews(images=torch.rand(1, 1, 3, 16, 16), poses=torch.eye(4)[None, None],
                          focal=torch.tensor([16.4]), principal=torch.tensor([[8.0, 8.0]]),
                          disparity=torch.rand(1, 1, 1, 16, 16) * 8 - 4)
    sources.poses[0, 0, 2, 3] = -1.3
    points = torch.rand(1, 64, 4, 3) - 0.5
    dirs = torch.nn.functional.normalize(torch.rand(1, 64, 3) - 0.5, dim=-1)
    outs = []
    with torch.no_grad():
        for pre in (src, out):
            rgb, sigma = pre.model.field(pre.model.encode(sources), "fine")(points, dirs)
            outs.append((rgb, sigma))
    assert torch.allclose(outs[0][0], outs[1][0], atol=2e-3) and not torch.equal(outs[0][0], outs[1][0])
    assert torch.allclose(outs[0][1], outs[1][1], atol=2e-3, rtol=2e-3)
    check = res.card["fp16_check"]
    assert 0 < check["max_abs_rgb"] <= exporter.FP16_TOLERANCE


def test_cards_from_eval_summary(exporter, run, tmp_path):
    best_sha = sha256_file(run / "checkpoints" / "best" / "model.safetensors")
    summary = _summary(tmp_path / "summary.json", best_sha)
    command = "depthnerf train --preset cpu-cars --data data/synth --depth bundled --out runs/cpu-cars-depth"
    res = exporter.export(run, "cpu-cars-depth", tmp_path / "ship", summary, command)
    card = json.loads(res.card_json.read_text())
    assert card["name"] == "cpu-cars-depth" and card["preset"] == "cpu-cars" and card["category"] == "cars"
    assert card["depth_estimator"] == "bundled" and card["step"] == 5 and card["dtype"] == "float16"
    assert card["sha256"] == sha256_file(res.weights) and card["size_bytes"] == res.weights.stat().st_size
    assert card["metrics"] == {"psnr": 23.4567, "ssim": 0.91234, "chamfer_l1": 0.0456, "fscore": 0.5}
    assert card["protocol"] == PROTOCOL
    assert card["evaluation"]["views_stride"] == 25 and card["evaluation"]["objects"] == 2
    assert "--views-stride 25" in card["eval_command"] and "--max-objects 2" in card["eval_command"]
    md = res.card_md.read_text()
    for text in ("# cpu-cars-depth", "depth-aware pixelNeRF", "**synthetic**", "**not** on real ShapeNet",
                 "3 synthetic cars train objects", "seed 0", "cpu-cars", "23.4567", "0.9123", PROTOCOL,
                 "split `test`, 2 objects, 20 scored views (view stride 25), 16x16 px", command,
                 card["eval_command"], "depthnerf synth --category cars --out $DATA --train-objects 3",
                 "## Intended use", "## Limitations", "MIT", card["sha256"]):
        assert text in md, text


def test_card_remakes_separate_evaluation_data(exporter, run, tmp_path):
    """A run scored on another dataset folder than it trained on: the card's reproduce block makes both, each with
    its own counts, and scores on the evaluation's; one folder for both keeps the single $DATA."""
    best_sha = sha256_file(run / "checkpoints" / "best" / "model.safetensors")
    test_card = {"generator": "depthnerf-synth-2/cars-r2", "framing": "srn", "seed": 4, "resolution": 16,
                 "counts": {"train": 0, "val": 0, "test": 50}, "styles": {"test": {}}}
    summary = _summary(tmp_path / "summary.json", best_sha, data_card={"root": "/data/test50", "card": test_card})
    res = exporter.export(run, "cpu-cars-depth", tmp_path / "ship", summary, "depthnerf train --data $DATA",
                          base=Path("/data"))
    card = json.loads(res.card_json.read_text())
    assert card["evaluation"]["dataset"] == {k: v for k, v in test_card.items() if k != "styles"}
    assert card["evaluation"]["data_root"] == "test50" and card["evaluation"]["train_data_root"] == "synth"
    assert "--data $EVAL_DATA" in card["eval_command"]
    block = res.card_md.read_text().split("## Reproduce")[1].split("## Intended use")[0]
    lines = [line for line in block.splitlines() if line and not line.startswith("```")]
    assert lines[0] == "DATA=synth"
    assert lines[1].startswith("depthnerf synth --category cars --out $DATA --train-objects 3 --val-objects 1 "
                               "--test-objects 2 --resolution 16 --seed 0")
    assert lines[2].startswith("depthnerf depth --data $DATA")
    i = lines.index("EVAL_DATA=test50")
    assert i > lines.index("depthnerf train --data $DATA")
    assert lines[i + 1] == ("depthnerf synth --category cars --out $EVAL_DATA --train-objects 0 --val-objects 0 "
                            "--test-objects 50 --resolution 16 --seed 4 --framing srn")
    assert lines[i + 2].startswith("depthnerf depth --data $EVAL_DATA --depth bundled")
    assert lines[i + 3] == card["eval_command"] and lines[i + 3].startswith("depthnerf eval --checkpoint cpu-cars")
    named = exporter.export(run, "cpu-cars-depth", tmp_path / "named", summary, "depthnerf train --data $DATA",
                            data_root="study/data")  # --data-root: one folder for both, the eval on it too
    text = named.card_md.read_text()
    assert "DATA=study/data" in text and "EVAL_DATA" not in text and "--data $DATA --split test" in text
    assert "EVAL_DATA" not in named.card["eval_command"]
    same = _summary(tmp_path / "same.json", best_sha, data_card={"root": "/data/synth", "card": test_card})
    res = exporter.export(run, "cpu-cars-depth", tmp_path / "ship2", same, "depthnerf train --data $DATA")
    text = res.card_md.read_text()
    assert "EVAL_DATA" not in text and "--data $DATA --split test" in text


def test_refuses_summary_of_another_checkpoint(exporter, run, tmp_path):
    summary = _summary(tmp_path / "summary.json", "0" * 64)
    with pytest.raises(exporter.DepthnerfError, match="evaluates checkpoint 000000000000"):
        exporter.export(run, "cpu-cars-depth", tmp_path / "ship", summary)
    assert not list((tmp_path / "ship").iterdir())  # nothing shipped, no staged file left
    assert exporter.main(["--run", str(run), "--name", "Bad Name", "--out", str(tmp_path / "ship")]) == 2


def test_latest_without_best(exporter, tmp_path):
    run = tiny_run(tmp_path / "run", tiny_config("chairs", "none"), steps=(3, 8), best=None)
    res = exporter.export(run, "cpu-chairs-baseline", tmp_path / "ship")
    with safe_open(str(res.weights), framework="pt") as f:
        meta = f.metadata()
    assert meta["step"] == "8" and meta["source_file"] == "checkpoints/step_00000008/model.safetensors"
    assert res.card["metrics"] is None and "Not evaluated" in res.card_md.read_text()
    assert "pixelNeRF baseline" in res.card_md.read_text()


def test_checkpoints_command_lists_card_metrics(exporter, run, tmp_path, monkeypatch, capsys):
    best_sha = sha256_file(run / "checkpoints" / "best" / "model.safetensors")
    ship = tmp_path / "ship"
    exporter.export(run, "cpu-cars-depth", ship, _summary(tmp_path / "summary.json", best_sha))
    exporter.export(tiny_run(tmp_path / "run2", tiny_config("chairs", "none"), best=None), "cpu-chairs-baseline", ship)
    monkeypatch.setattr(pretrained, "SHIPPED_DIR", ship)
    assert cli_main(["checkpoints"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("cpu-cars-depth: preset cpu-cars, category cars, depth prior bundled "
                               "(bundled.safetensors weights), 5 steps; "
                               "psnr 23.46, ssim 0.9123, chamfer_l1 0.0456, fscore 0.5")
    assert PROTOCOL in lines[0] and "cpu-cars-depth.md" in lines[0]
    assert "cpu-chairs-baseline: preset cpu-chairs" in lines[1] and "no metrics recorded" in lines[1]
    assert cli_main(["checkpoints", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert rows[0]["metrics"]["psnr"] == 23.4567 and rows[1]["metrics"] is None
    assert rows[0]["facing_head"] is False and "facing head" not in "".join(lines)
    assert load_pretrained("cpu-cars-depth").step == 5  # the shipped name resolves


def test_cards_hold_relative_paths(exporter, run, tmp_path):
    """Paths the export sees absolute (summary, data root, run) land in the cards relative to the base; the home
    directory in eval messages becomes ~."""
    best_sha = sha256_file(run / "checkpoints" / "best" / "model.safetensors")
    home = str(Path.home())
    (tmp_path / "study" / "eval").mkdir(parents=True)
    summary = _summary(tmp_path / "study" / "eval" / "summary.json", best_sha,
                       data_card={"root": str(tmp_path / "study" / "data")},
                       lpips_status=f"unavailable: not found ({home}/.cache/torch/vgg.pth)")
    res = exporter.export(run.resolve(), "cpu-cars-depth", tmp_path / "ship", summary.resolve(), "cmd",
                          data_root=str(tmp_path / "study" / "data"), base=tmp_path)
    card = json.loads(res.card_json.read_text())
    assert card["evaluation"]["summary"] == "study/eval/summary.json"
    assert card["evaluation"]["data_root"] == card["data_root"] == "study/data"
    assert not Path(card["run_path"]).is_absolute() and card["run_path"].endswith("cpu-cars-depth-run")
    assert card["evaluation"]["lpips_status"] == "unavailable: not found (~/.cache/torch/vgg.pth)"
    assert card["pixel_center"] == 0.0
    text = res.card_json.read_text() + res.card_md.read_text()
    assert str(tmp_path) not in text and home + "/" not in text


def test_fix_cards_rewrites_paths_not_weights(exporter, run, tmp_path):
    """scripts/fix_checkpoint_cards.py turns an old card's absolute paths relative, records the framing, and
    leaves the weights byte-identical."""
    best_sha = sha256_file(run / "checkpoints" / "best" / "model.safetensors")
    res = exporter.export(run, "cpu-cars-depth", tmp_path / "ship", _summary(tmp_path / "s.json", best_sha), "cmd",
                          data_root="study/data")
    card = json.loads(res.card_json.read_text())
    old_summary = "/work/study/eval/cars-bundled/summary.json"
    card["evaluation"].update(summary=old_summary, data_root="/work/study/data")
    for key in ("pixel_center", "framing", "generator"):  # a card written before these fields existed
        del card[key]
    res.card_json.write_text(json.dumps(card, indent=1))
    md = res.card_md.read_text().replace(" --framing legacy", "").replace(
        "framing `legacy` (docs/data.md), pixel centres read as `data.pixel_center` 0.0, ", "")
    assert "framing" not in md
    res.card_md.write_text(md + f"\nsee {old_summary}\n")
    weights_sha = sha256_file(res.weights)
    fixer = load_script("fix_checkpoint_cards")
    assert fixer.main([str(res.card_json), "--framing", "legacy", "--relative-to", "/work"]) == 0
    fixed = json.loads(res.card_json.read_text())
    assert fixed["evaluation"]["summary"] == "study/eval/cars-bundled/summary.json"
    assert fixed["evaluation"]["data_root"] == "study/data"
    assert fixed["framing"] == "legacy" and fixed["pixel_center"] == 0.0
    assert fixed["generator"] == "depthnerf-synth-1/test"  # read from the model card
    new_md = res.card_md.read_text()
    assert "/work/" not in new_md and "see study/eval/cars-bundled/summary.json" in new_md
    assert "generator `depthnerf-synth-1/test`, framing `legacy`" in new_md and "--seed 0 --framing legacy" in new_md
    assert sha256_file(res.weights) == weights_sha


def test_card_of_a_warm_started_run_names_its_source(exporter, run, tmp_path):
    warm = tmp_path / "warm-run"
    shutil.copytree(run, warm)
    plain = exporter.export(warm, "cpu-cars-depth", tmp_path / "plain")
    assert "init_from" not in plain.card and "Warm start" not in plain.card_md.read_text()
    record = {"source": "cpu-cars-sym-pp", "path": "/x/cpu-cars-sym-pp.safetensors", "sha256": "ab" * 32, "step": 3500}
    (warm / "init_from.json").write_text(json.dumps(record))
    res = exporter.export(warm, "cpu-cars-depth", tmp_path / "ship")
    assert res.card["init_from"] == {"source": "cpu-cars-sym-pp", "step": 3500, "total_steps": 3500,
                                     "sha256": "ab" * 32}  # the source file is gone: its own steps
    assert "continue from the network weights of `cpu-cars-sym-pp` (step 3500, sha256 `abababababababab...`)" \
        in res.card_md.read_text()
    assert "| training steps | 3505 in all: 5 on top of a warm start from a model trained 3500 steps |" \
        in res.card_md.read_text()
    listed = describe("cpu-cars-depth", res.weights)
    assert listed["steps"] == 5 and listed["warm_start_steps"] == 3500 and listed["total_steps"] == 3505
    assert describe("cpu-cars-depth", plain.weights)["warm_start_steps"] is None
    again = exporter.export(warm, "cpu-cars-sym-pp", tmp_path / "again")  # a shipped name continued: its successor
    assert "continue from the network weights of the `cpu-cars-sym-pp` shipped before this one (step 3500, sha256 " \
        "`abababababababab...`)" in again.card_md.read_text()
    copy = tmp_path / "previous.safetensors"  # a run started from a copy of the file the export replaces
    shutil.copyfile(again.weights, copy)
    (warm / "init_from.json").write_text(json.dumps({"source": str(copy), "path": str(copy), "step": 5,
                                                     "sha256": sha256_file(copy)}))
    successor = exporter.export(warm, "cpu-cars-sym-pp", tmp_path / "again")
    assert successor.card["init_from"]["source"] == "cpu-cars-sym-pp"
    assert "the `cpu-cars-sym-pp` shipped before this one (step 5, sha256" in successor.card_md.read_text()
    elsewhere = exporter.export(warm, "cpu-cars-sym-pp", tmp_path / "fresh")  # nothing to replace: the path stays
    assert elsewhere.card["init_from"]["source"].endswith("previous.safetensors")


def test_warm_start_from_a_run_folder_is_written_relative(exporter, run, tmp_path):
    warm = tmp_path / "warm-run"
    shutil.copytree(run, warm)
    start = tmp_path / "runs" / "cars-bundled-w"  # init_from.json records a run folder by its absolute path
    (warm / "init_from.json").write_text(json.dumps({"source": str(start), "sha256": "cd" * 32, "step": 2000}))
    res = exporter.export(warm, "cpu-cars-depth", tmp_path / "ship", base=tmp_path)
    assert res.card["init_from"]["source"] == "runs/cars-bundled-w"
    assert str(tmp_path) not in res.card_md.read_text()


def test_an_unfinished_run_is_refused_unless_asked_for(exporter, tmp_path):
    """A run whose newest checkpoint is short of its ``--max-steps`` (stopped early, or still training) is not
    exported as if finished: refused in one line, or with --allow-unfinished exported with cards that say so."""
    run = tiny_run(tmp_path / "run", tiny_config("chairs", "none"), steps=(3, 8), best=3, max_steps=20)
    with pytest.raises(exporter.DepthnerfError, match=r"not finished \(its newest checkpoint is step 8 of 20"):
        exporter.export(run, "cpu-chairs-baseline", tmp_path / "ship")
    assert not (tmp_path / "ship").exists() or not list((tmp_path / "ship").iterdir())
    assert exporter.main(["--run", str(run), "--name", "cpu-chairs-baseline", "--out", str(tmp_path / "ship")]) == 2
    res = exporter.export(run, "cpu-chairs-baseline", tmp_path / "ship", allow_unfinished=True)
    assert res.card["unfinished"] == {"stopped_at": 8, "max_steps": 20} and res.card["step"] == 3  # best, as before
    assert "Schedule: 20 steps (the run stopped at step 8: exported unfinished)" in res.card_md.read_text()
    assert load_pretrained(res.weights).step == 3


def test_refuses_summary_of_another_depth_prior(exporter, run, tmp_path):
    """``depthnerf eval --depth`` / ``--depth-checkpoint`` score the checkpoint with a prior it does not ship with:
    such a summary's metrics are not the shipped model's."""
    best_sha = sha256_file(run / "checkpoints" / "best" / "model.safetensors")
    oracle = _summary(tmp_path / "oracle.json", best_sha, depth_prior="oracle", method="depth-aware (oracle)")
    with pytest.raises(exporter.DepthnerfError, match="with the oracle depth prior, but it ships with bundled"):
        exporter.export(run, "cpu-cars-depth", tmp_path / "ship", oracle)
    trained = load_pretrained(run).spec.prior_weights_hash or json.loads((run / "prior.json").read_text())[
        "weights_hash"]  # the run's record of the prior it trained with, where the spec has none
    other = _summary(tmp_path / "other.json", best_sha,
                     depth_prior_provenance={"estimator": "bundled", "checkpoint": "srn", "weights_hash": "cd" * 32})
    with pytest.raises(exporter.DepthnerfError, match="with other depth weights .srn, sha256 cdcdcdcdcdcd"):
        exporter.export(run, "cpu-cars-depth", tmp_path / "ship", other)
    assert not list((tmp_path / "ship").iterdir())
    same = _summary(tmp_path / "same.json", best_sha,
                    depth_prior_provenance={"estimator": "bundled", "checkpoint": "x", "weights_hash": trained})
    assert trained and exporter.export(run, "cpu-cars-depth", tmp_path / "ship", same).card["metrics"]["psnr"] == 23.4567


def test_a_card_that_fails_leaves_the_shipped_trio_as_it_was(exporter, run, tmp_path, monkeypatch):
    """Re-exporting over a shipped name: a card that cannot be written (here its Markdown) leaves the weights and
    both cards byte-identical, with no staged file, so the three never describe different weights."""
    ship = tmp_path / "ship"
    exporter.export(run, "cpu-cars-depth", ship)
    before = {p.name: p.read_bytes() for p in ship.iterdir()}
    assert sorted(before) == ["cpu-cars-depth.json", "cpu-cars-depth.md", "cpu-cars-depth.safetensors"]
    other = tmp_path / "other-run"
    shutil.copytree(run, other)
    shutil.rmtree(other / "checkpoints" / "best")  # the latest checkpoint: other weights than the shipped ones

    def broken(*args, **kwargs):
        raise exporter.DepthnerfError("card: cannot be written")

    monkeypatch.setattr(exporter, "model_card", broken)
    with pytest.raises(exporter.DepthnerfError, match="card: cannot be written"):
        exporter.export(other, "cpu-cars-depth", ship)
    assert {p.name: p.read_bytes() for p in ship.iterdir()} == before


def test_a_chain_of_warm_starts_counts_every_step(exporter, run, tmp_path):
    """Steps in all follow a chain of warm starts: an exported model records its total in its metadata; a run
    warm-started from it adds its own steps; a card written before the field that describes those very weights
    (same SHA-256) supplies the total of weights that lack it, and a card of other weights does not."""
    from depthnerf.train.warm_start import steps_in_all

    first = exporter.export(run, "first", tmp_path / "a")  # 5 steps from scratch
    _, meta = ckpt.read_weights(first.weights)
    assert meta["total_steps"] == "5" and first.card["total_steps"] == 5
    assert steps_in_all(first.weights, meta, sha256_file(first.weights)) == 5
    second_run = tmp_path / "second-run"
    shutil.copytree(run, second_run)
    record = {"source": str(first.weights), "path": str(first.weights), "sha256": sha256_file(first.weights),
              "step": 5}  # as a run warm-started before the field recorded it: resolved from the file
    (second_run / "init_from.json").write_text(json.dumps(record))
    second = exporter.export(second_run, "second", tmp_path / "b")
    assert second.card["total_steps"] == 10 and ckpt.read_weights(second.weights)[1]["total_steps"] == "10"
    assert describe("second", second.weights)["total_steps"] == 10
    (second_run / "init_from.json").write_text(json.dumps({**record, "total_steps": 4000}))  # recorded at the start
    assert exporter.export(second_run, "third", tmp_path / "c").card["total_steps"] == 4005

    legacy = tmp_path / "legacy.safetensors"  # weights without the metadata, beside a card that gives the total
    shutil.copy(run / "checkpoints" / "best" / "model.safetensors", legacy)
    _, legacy_meta = ckpt.read_weights(legacy)
    sha = sha256_file(legacy)
    legacy.with_suffix(".json").write_text(json.dumps({"sha256": sha, "total_steps": 7000}))
    assert steps_in_all(legacy, legacy_meta, sha) == 7000
    legacy.with_suffix(".json").write_text(json.dumps({"sha256": "0" * 64, "total_steps": 7000}))
    assert steps_in_all(legacy, legacy_meta, sha) == 5


def test_a_run_checkpoint_counts_its_runs_warm_start(exporter, run, tmp_path):
    """``--init-from RUN`` resolves to a checkpoint inside the run folder, whose metadata has no ``total_steps``: the
    steps in all are its own plus the ``total_steps`` of the run's ``init_from.json`` (else its ``step``); a record
    without a count is an error naming it, and a copy of the weights outside a run counts its own steps."""
    from depthnerf.pretrained.load import resolve_checkpoint
    from depthnerf.train.warm_start import steps_in_all

    chained = tmp_path / "chained-run"
    shutil.copytree(run, chained)
    weights = resolve_checkpoint(str(chained))
    _, meta = ckpt.read_weights(weights)
    sha = sha256_file(weights)
    assert "total_steps" not in meta and steps_in_all(weights, meta, sha) == 5  # trained from scratch
    (chained / "init_from.json").write_text(json.dumps({"step": 3000, "total_steps": 11000}))
    assert steps_in_all(weights, meta, sha) == 11005
    (chained / "init_from.json").write_text(json.dumps({"step": 3000}))  # a record that predates the field
    assert steps_in_all(weights, meta, sha) == 3005
    (chained / "init_from.json").write_text("{not json")
    with pytest.raises(exporter.DepthnerfError, match="init_from.json: not a readable warm-start record"):
        steps_in_all(weights, meta, sha)
    loose = tmp_path / "loose" / "model.safetensors"
    loose.parent.mkdir()
    shutil.copy(weights, loose)
    assert steps_in_all(loose, meta, sha) == 5


def test_fix_cards_records_a_chains_total_steps(exporter, run, tmp_path):
    """``--total-steps`` gives a card exported before cards counted a chain its steps in all (the JSON, the
    "training steps" row of an old-format Markdown card, the listing), weights untouched; a card without a warm
    start, or a total below the run's own steps, is refused in one line."""
    warm = tmp_path / "warm-run"
    shutil.copytree(run, warm)
    (warm / "init_from.json").write_text(json.dumps({"source": "prev", "sha256": "ab" * 32, "step": 3000}))
    res = exporter.export(warm, "cpu-cars-sym-pp", tmp_path / "ship")
    card = json.loads(res.card_json.read_text())
    del card["total_steps"], card["init_from"]["total_steps"]  # as written before the field
    res.card_json.write_text(json.dumps(card, indent=1))
    old_row = "| training steps | 5 (on top of a warm start from a 3000-step model) |"
    md = re.sub(r"^\| training steps \|.*$", lambda _: old_row, res.card_md.read_text(), flags=re.M)
    res.card_md.write_text(md)
    weights_sha = sha256_file(res.weights)
    fixer = load_script("fix_checkpoint_cards")
    assert fixer.main([str(res.card_json), "--total-steps", "8005"]) == 0
    fixed = json.loads(res.card_json.read_text())
    assert fixed["total_steps"] == 8005 and fixed["init_from"]["total_steps"] == 8000
    new_md = res.card_md.read_text()
    assert old_row not in new_md
    assert "| training steps | 8005 in all: 5 on top of a warm start from a model trained 8000 steps |" in new_md
    assert describe("cpu-cars-sym-pp", res.weights)["total_steps"] == 8005 and sha256_file(res.weights) == weights_sha
    plain = exporter.export(run, "plain", tmp_path / "plain")
    assert fixer.main([str(plain.card_json), "--total-steps", "8005"]) == 2
    assert fixer.main([str(res.card_json), "--total-steps", "4"]) == 2


def test_card_names_the_parameters_a_run_held_fixed(exporter, run, tmp_path):
    """A run trained with ``--schedule.freeze`` says so on its card's schedule line (and a run without does not)."""
    plain = exporter.export(run, "cpu-cars-depth", tmp_path / "plain")
    assert "--schedule.freeze" not in plain.card_md.read_text()
    cfg = tiny_config("cars", "bundled", tiny_bundled(tmp_path / "bundled.safetensors"))
    cfg = dataclasses.replace(cfg, schedule=dataclasses.replace(cfg.schedule, freeze=("encoder", "fine.lin_out")))
    res = exporter.export(tiny_run(tmp_path / "frozen-run", cfg), "cpu-cars-depth", tmp_path / "ship")
    assert "; parameters held fixed (`--schedule.freeze encoder,fine.lin_out`)." in res.card_md.read_text()
