"""Training batches (:mod:`depthnerf.train.batching`) against the schedule of its module docstring, checked by
brute force: item seeds, epoch-wise permutations, view picks and box sampling counted over many draws."""

from __future__ import annotations

import pytest
import torch

from depthnerf.train.batching import BatchPlan, StepSampler, item_seed, pick_views, sample_pixels, step_keys


def test_item_seeds_are_63_bit_and_differ_between_items_steps_and_runs():
    """Every seed is in ``[0, 2**63)``, and no two of (seed, step, k) over a grid share one (a brute-force set)."""
    seeds = {(s, t, k): item_seed(s, t, k) for s in (0, 1, 2**40 + 7) for t in (-1, 0, 1, 5000) for k in range(8)}
    assert all(0 <= v < 2**63 for v in seeds.values())
    assert len(set(seeds.values())) == len(seeds)


def test_each_item_of_a_step_has_its_own_seed_even_for_the_same_object():
    """Item ``k`` of step ``s`` is seeded by ``item_seed(seed, s, k)`` (the position, not the object): a step that
    wraps an epoch may draw one object twice, and its two items still get their own views and rays."""
    plan = BatchPlan(num_objects=3, seed=11, bbox_steps=0, objects_phase1=4, objects_phase2=4)
    for step in range(6):
        keys = step_keys(plan, step)
        assert [key.seed for key in keys] == [item_seed(11, step, k) for k in range(4)]
        assert len({key.seed for key in keys}) == 4
    assert any(len(set(plan.objects(step))) < 4 for step in range(6))  # 4 of 3 objects: some step repeats one


def test_every_epoch_draws_its_own_permutation():
    """Objects are drawn without replacement within an epoch, in an order that changes from epoch to epoch (for 10
    objects, two equal orders of 10! would be a coincidence); and a plan with another seed draws another order."""
    plan = BatchPlan(num_objects=10, seed=5, bbox_steps=0, objects_phase1=5, objects_phase2=5)
    drawn = [o for step in range(8) for o in plan.objects(step)]
    epochs = [tuple(drawn[10 * e:10 * (e + 1)]) for e in range(4)]
    assert all(sorted(e) == list(range(10)) for e in epochs) and len(set(epochs)) == 4
    other = BatchPlan(num_objects=10, seed=6, bbox_steps=0, objects_phase1=5, objects_phase2=5)
    assert [other.objects(s) for s in (0, 1)] != [plan.objects(s) for s in (0, 1)]


def test_the_box_phase_ends_exactly_at_bbox_steps():
    """Steps ``0 .. bbox_steps - 1`` sample inside boxes, later ones from the whole image."""
    plan = BatchPlan(num_objects=4, seed=0, bbox_steps=3, objects_phase1=2, objects_phase2=4)
    assert [step_keys(plan, s)[0].use_bbox for s in range(5)] == [True, True, True, False, False]
    assert [len(step_keys(plan, s)) for s in range(5)] == [2, 2, 2, 4, 4]


@pytest.mark.parametrize("num_views, num_targets", [(5, 2), (5, 4), (5, 10), (5, 0), (2, 1), (1, 0)])
def test_picked_targets_are_distinct_other_views(num_views, num_targets):
    """The source is never a target; targets are distinct; ``num_targets`` of them (0 or more than there are: all
    the others)."""
    gen = torch.Generator().manual_seed(1)
    for _ in range(20):
        src, targets = pick_views(num_views, num_targets, gen)
        assert len(src) == 1 and src[0] not in targets and len(set(targets)) == len(targets)
        want = num_views - 1 if num_targets <= 0 else min(num_targets, num_views - 1)
        assert len(targets) == want and set(targets) <= set(range(num_views))


def test_box_sampling_reaches_every_pixel_of_an_inclusive_box_and_only_those():
    """Boxes are ``x0, y0, x1, y1`` inclusive: over many draws, the set of (row, col) pairs in each view is exactly
    the box's pixels, counted by a loop."""
    gen = torch.Generator().manual_seed(0)
    boxes = torch.tensor([[2, 9, 4, 11], [6, 1, 6, 3]])
    view, row, col = sample_pixels(6000, (2, 12, 10), boxes, gen)
    for v, (x0, y0, x1, y1) in enumerate(boxes.tolist()):
        got = set(zip(row[view == v].tolist(), col[view == v].tolist(), strict=True))
        assert got == {(r, c) for r in range(y0, y1 + 1) for c in range(x0, x1 + 1)}


def test_whole_image_sampling_reaches_every_pixel_of_a_non_square_image():
    """Without boxes, rows span the height and columns the width (a 3 x 7 image, every pixel drawn)."""
    gen = torch.Generator().manual_seed(0)
    view, row, col = sample_pixels(3000, (2, 3, 7), None, gen)
    assert set(zip(row.tolist(), col.tolist(), strict=True)) == {(r, c) for r in range(3) for c in range(7)}
    assert set(view.tolist()) == {0, 1}


def test_the_step_sampler_yields_one_batch_per_step_from_start_to_stop():
    plan = BatchPlan(num_objects=6, seed=2, bbox_steps=1, objects_phase1=2, objects_phase2=2)
    sampler = StepSampler(plan, start=3, stop=7, rank=1, world=2)
    batches = list(sampler)
    assert len(sampler) == len(batches) == 4 and len(StepSampler(plan, 5, 2)) == 0
    assert batches == [step_keys(plan, s, 1, 2) for s in range(3, 7)]
