"""``--data.channel_permute``: an item's colour channels permuted, source views and target rays in the same order,
and nothing else about the item changed."""

from __future__ import annotations

import pytest
import torch
from fixtures_srn import make_srn_fixture
from test_view_store import scramble_colours

from depthnerf.data.srn import index_split
from depthnerf.depth.prior import PriorConfig, open_prior
from depthnerf.errors import DepthnerfError
from depthnerf.train.batching import ItemKey
from depthnerf.train.config import check_config, preset
from depthnerf.train.items import CHANNEL_ORDERS, TrainItems, permuted_channels


def test_the_orders_drawn_are_the_five_permutations_at_the_fraction_asked():
    gen = torch.Generator().manual_seed(0)
    orders = [tuple(permuted_channels(gen, 0.5)) for _ in range(3000)]
    assert set(orders) == {(0, 1, 2), *CHANNEL_ORDERS} and len(CHANNEL_ORDERS) == 5
    assert 1350 < orders.count((0, 1, 2)) < 1650  # binomial(3000, 1/2): sd 27
    for order in CHANNEL_ORDERS:  # binomial(3000, 1/10): sd 16
        assert 220 < orders.count(order) < 380
    assert all(permuted_channels(gen, 1.0) != [0, 1, 2] for _ in range(200))
    assert all(permuted_channels(gen, 0.0) == [0, 1, 2] for _ in range(200))


def test_an_item_is_the_plain_item_with_its_channels_permuted(tmp_path):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=5, size=16, with_depth=True)
    scramble_colours(root)
    records = index_split(root, "cars", "train").objects
    prior = open_prior(PriorConfig("oracle"), data_root=root, resolution=16, records=records)
    common = dict(resolution=16, target_views=2, rays_per_object=64, target_priors=False, pixel_center=0.5)
    plain, permuted = TrainItems(records, prior, **common), TrainItems(records, prior, **common, channel_permute=1.0)
    seen = set()
    for seed in range(12):
        key = ItemKey(object_index=seed % 2, seed=seed, use_bbox=False, sources=1 + seed % 2)
        a, b = plain[key], permuted[key]
        order = next(list(o) for o in CHANNEL_ORDERS if torch.equal(b.source.images, a.source.images[:, :, o]))
        seen.add(tuple(order))
        assert torch.equal(b.target_rgb, a.target_rgb[..., order])
        for name in ("ray_origins", "ray_dirs", "target_fg", "target_cos"):
            assert torch.equal(getattr(a, name), getattr(b, name))
        assert torch.equal(a.source.disparity, b.source.disparity) and torch.equal(a.source.poses, b.source.poses)
    assert len(seen) >= 3


def test_the_fraction_is_checked():
    cfg = preset("cpu-chairs")
    assert cfg.data.channel_permute == 0.0
    for bad in (-0.1, 1.5, float("nan")):
        cfg.data.channel_permute = bad
        with pytest.raises(DepthnerfError, match="--data.channel_permute must be in"):
            check_config(cfg)
