"""Several source views per training item (``--data.source_views``, pixelNeRF's ``--nviews``): the item holds
exactly the views its draw names, the view store gives the same items, one source draws as before, several counts
draw one per step (the same for every object and rank), and a run trained on two views is evaluated on two
(``eval --input-views``)."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from fixtures_srn import make_srn_fixture
from safetensors.torch import load_file
from test_eval_protocol import TINY, cli
from test_view_store import assert_same_items, scramble_colours

from depthnerf.data.srn import index_split, load_object
from depthnerf.data.view_store import ViewStore
from depthnerf.depth.prior import PriorConfig, open_prior
from depthnerf.errors import DepthnerfError
from depthnerf.train.batching import BatchPlan, ItemKey, item_seed, pick_views, step_keys
from depthnerf.train.config import check_config, from_dict_config, preset
from depthnerf.train.items import TrainItems


def test_sources_and_targets_are_one_permutation_and_one_source_draws_as_before():
    for sources in (1, 2, 3):
        gen, ref = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
        src, targets = pick_views(6, 0, gen, sources)
        perm = torch.randperm(6, generator=ref).tolist()
        assert src == perm[:sources] and targets == perm[sources:]
    src, targets = pick_views(6, 2, torch.Generator().manual_seed(5), 2)
    assert len(targets) == 2 and not set(src) & set(targets)


def test_an_item_holds_the_drawn_source_views_and_the_store_agrees(tmp_path):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=5, size=16, with_depth=True)
    scramble_colours(root)
    records = index_split(root, "cars", "train").objects
    prior = open_prior(PriorConfig("oracle"), data_root=root, resolution=16, records=records)
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure(records)
    common = dict(resolution=16, target_views=2, rays_per_object=32, target_priors=False, pixel_center=0.5)
    files = TrainItems(records, prior, **common)
    key = ItemKey(object_index=1, seed=11, use_bbox=False, sources=2)
    src, _ = pick_views(5, 2, torch.Generator().manual_seed(11), 2)
    want = load_object(records[1], src, resolution=16, pixel_center=0.5)
    item = files[key]
    assert item.source.images.shape == (1, 2, 3, 16, 16) and item.source.disparity.shape == (1, 2, 1, 16, 16)
    assert torch.equal(item.source.images[0], want.images) and torch.equal(item.source.poses[0], want.poses)
    plan = BatchPlan(num_objects=2, seed=3, bbox_steps=1, objects_phase1=2, objects_phase2=2, source_views=(1, 2))
    keys = [k for step in range(6) for k in step_keys(plan, step)]
    assert {k.sources for k in keys} == {1, 2}
    assert_same_items(files, TrainItems(records, prior, **common, view_store=store), keys)


def test_a_two_view_run_trains_and_is_evaluated_on_two_views(tmp_path, capsys):
    root = tmp_path / "data"
    make_srn_fixture(root, "cars", {"train": 2}, views=3, size=32, with_mask=True)
    make_srn_fixture(root, "cars", {"test": 1}, views=66, size=32, with_mask=True)
    run = tmp_path / "run"
    assert cli("train", "--depth", "none", "--data", root, "--out", run, *TINY, "--data.source_views", "2") == 0
    assert json.loads((run / "config.json").read_text())["data"]["source_views"] == [2]
    out = tmp_path / "eval"
    assert cli("eval", "--run", run, "--out", out, "--input-views", "64", "20", "--views-stride", "32",
               "--no-mesh", "--no-progress") == 0
    assert json.loads((out / "summary.json").read_text())["input_views"] == [64, 20]
    capsys.readouterr()
    assert cli("train", "--depth", "none", "--data", root, "--out", tmp_path / "run3", *TINY,
               "--data.source_views", "1,3") == 2
    err = capsys.readouterr().err
    assert ("has 3 views; a training object needs at least 4 (--data.source_views 1,3 conditions on up to 3, and a "
            "target)") in err
    assert err.count("\n") == 1


def test_one_count_draws_nothing_and_the_keys_are_the_papers():
    for step in range(5):
        one = BatchPlan(num_objects=7, seed=4, bbox_steps=2, objects_phase1=3, objects_phase2=3)
        two = BatchPlan(num_objects=7, seed=4, bbox_steps=2, objects_phase1=3, objects_phase2=3, source_views=(2,))
        want = [ItemKey(o, item_seed(4, step, k), step < 2) for k, o in enumerate(one.objects(step))]
        assert step_keys(one, step) == want
        assert step_keys(two, step) == [ItemKey(k.object_index, k.seed, k.use_bbox, 2) for k in want]


def test_several_counts_draw_one_per_step_uniformly_for_every_rank():
    plan = BatchPlan(num_objects=8, seed=9, bbox_steps=0, objects_phase1=4, objects_phase2=4, source_views=(1, 2, 3))
    single = BatchPlan(num_objects=8, seed=9, bbox_steps=0, objects_phase1=4, objects_phase2=4)
    counts = []
    for step in range(600):
        ranks = [step_keys(plan, step, rank, 2) for rank in range(2)]
        per_key = {k.sources for keys in ranks for k in keys}
        assert len(per_key) == 1  # every object of the step, on every rank
        counts.append(per_key.pop())
        # the objects, seeds and boxes are those of a one-count run: the count's draw is a generator of its own
        assert [(k.object_index, k.seed) for keys in ranks for k in keys] == \
            [(k.object_index, k.seed) for k in step_keys(single, step)]
    assert counts == [plan.sources(step) for step in range(600)]  # a pure function of (seed, step): exact resume
    for c in (1, 2, 3):  # binomial(600, 1/3): mean 200, sd 11.5
        assert 140 < counts.count(c) < 260


def test_source_view_counts_in_the_config():
    cfg = preset("cpu-cars")
    assert cfg.data.source_views == (1,)
    cfg.data.source_views = (1, 2)
    check_config(cfg)
    for bad, said in (((), "got nothing"), ((0,), "got 0"), ((1, 1), "got 1,1"), ((2, -1), "got 2,-1")):
        cfg.data.source_views = bad
        with pytest.raises(DepthnerfError, match=f"--data.source_views must list .*{said}$"):
            check_config(cfg)
    data = json.loads(json.dumps(dataclasses.asdict(preset("cpu-cars"))))
    data["data"]["source_views"] = 2  # a config written when the field held one number
    assert from_dict_config(data).data.source_views == (2,)
    data["data"]["source_views"] = "2"
    with pytest.raises(DepthnerfError, match="source_views: expected a list"):
        from_dict_config(data)


def test_a_run_on_one_or_two_views_resumes_exactly(tmp_path):
    root = tmp_path / "data"
    make_srn_fixture(root, "cars", {"train": 2}, views=3, size=32, with_mask=True)
    mixed = [*TINY, "--data.source_views", "1,2", "--checkpoint-every", "2", "--log.log_every", "1"]
    straight, parts = tmp_path / "straight", tmp_path / "parts"
    assert cli("train", "--depth", "none", "--data", root, "--out", straight, *mixed, "--max-steps", "4") == 0
    assert json.loads((straight / "config.json").read_text())["data"]["source_views"] == [1, 2]
    assert cli("train", "--depth", "none", "--data", root, "--out", parts, *mixed, "--max-steps", "2") == 0
    assert cli("train", "--depth", "none", "--data", root, "--out", parts, "--resume", "--max-steps", "4",
               "--no-progress") == 0
    plan = BatchPlan(num_objects=2, seed=preset("cpu-cars").seed, bbox_steps=0, objects_phase1=1, objects_phase2=1,
                     source_views=(1, 2))
    assert {plan.sources(step) for step in range(4)} == {1, 2}  # the run saw both counts
    losses = [[json.loads(line)["loss"] for line in (run / "metrics.jsonl").read_text().splitlines()]
              for run in (straight, parts)]
    assert len(losses[0]) == 4 and losses[0] == losses[1]
    weights = [load_file(run / "checkpoints" / "step_00000004" / "model.safetensors") for run in (straight, parts)]
    assert all(torch.equal(weights[0][name], weights[1][name]) for name in weights[0])


def test_validation_targets_leave_out_every_input_view():
    from depthnerf.data.protocol import validation_targets, validation_views_note

    assert validation_targets([0, 104, 200], 251, (64, 104)) == [0, 200]
    assert validation_targets([64, 104], 251, (64, 104)) == [65]  # nothing left: the first non-input after 64
    assert validation_targets([1, 2], 3, (2, 0)) == [1] and validation_targets([2, 0], 3, (2, 0)) == [1]
    for views, count in (([0, 125, 200], 251), ([64], 251), ([1, 999], 3), ([0], 3)):  # None: as before
        assert validation_targets(views, count, None) == validation_targets(views, count)
    assert validation_views_note([0, 104], [("a", 251)], (64, 104)) == (
        "note: --log.val_views 0,104: a has 251 views, input views 64,104; validation renders its views 0")


def test_a_two_view_run_validates_on_two_views_and_a_missing_one_is_one_line(tmp_path, capsys):
    root = tmp_path / "data"
    make_srn_fixture(root, "cars", {"train": 2, "val": 1}, views=3, size=32, with_mask=True)
    run = tmp_path / "run"
    val = ["--log.val_every", "1", "--log.val_objects", "1", "--log.val_views", "0,2"]
    flags = [*TINY, "--data.source_views", "2", *val, "--log.val_input_views", "0,1"]
    assert cli("train", "--depth", "none", "--data", root, "--out", run, *flags) == 0
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert any(math.isfinite(row.get("val_psnr", math.nan)) for row in rows), rows
    assert "note: --log.val_views 0,2: " in capsys.readouterr().err  # view 0 is an input: view 2 alone is scored
    obj = next((root / "cars_val").iterdir())
    assert cli("train", "--depth", "none", "--data", root, "--out", tmp_path / "r2", *flags[:-1], "0,5") == 2
    assert capsys.readouterr().err == (f"error: {obj}: input view 5 does not exist: the object has 3 views (0-2) "
                                       "(--log.val_input_views)\n")
    assert not (tmp_path / "r2").exists()
    assert cli("train", "--depth", "none", "--data", root, "--out", tmp_path / "r3", *flags[:-1], "1,1") == 2
    assert capsys.readouterr().err == "error: --log.val_input_views names a view twice: 1 1\n"


def test_an_out_of_memory_line_names_the_source_views():
    from depthnerf.train.memory import step_sizes

    cfg = preset("cpu-chairs")
    assert "source views" not in step_sizes(cfg, 1, 2)
    cfg.data.source_views = (1, 2)
    assert ("n_gaussian 8), each object on up to 2 source views (--data.source_views 1,2), at --data.resolution 64"
            in step_sizes(cfg, 1, 2))
