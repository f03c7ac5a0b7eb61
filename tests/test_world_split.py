"""A world size the global batch does not divide is refused in one line before a run starts (every rank takes an
equal share of a step's objects: docs/training.md, "Real SRN on GPUs")."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from fixtures_checkpoints import tiny_config, tiny_run

from depthnerf.distributed import DistInfo
from depthnerf.errors import DepthnerfError
from depthnerf.train.batching import check_world_split, shard
from depthnerf.train.config import preset
from depthnerf.train.loop import train


def schedule_split(name: str, world: int) -> None:
    s = preset(name).schedule
    check_world_split(s.bbox_steps, s.objects_phase1, s.objects_phase2, s.max_steps, world)


def test_the_paper_batches_split_over_1_2_and_4_ranks_only():
    for world in (1, 2, 4):
        schedule_split("paper-cars", world)
    for world in (3, 8, 16):
        with pytest.raises(DepthnerfError) as err:
            schedule_split("paper-cars", world)
        message = str(err.value)
        assert message.startswith(f"--schedule.objects_phase1 4: a global batch of 4 objects does not split over "
                                  f"{world} ranks; launch 1, 2, 4 processes"), message
        assert "\n" not in message


def test_only_the_phases_a_run_reaches_are_checked():
    check_world_split(bbox_steps=0, objects_phase1=3, objects_phase2=8, max_steps=100, world=8)  # no bbox phase
    check_world_split(bbox_steps=100, objects_phase1=8, objects_phase2=3, max_steps=100, world=8)  # no phase 2
    with pytest.raises(DepthnerfError, match=r"^--schedule.objects_phase2 6: .* over 4 ranks; launch 1, 2 "):
        check_world_split(bbox_steps=10, objects_phase1=8, objects_phase2=6, max_steps=100, world=4)


def test_a_resume_checks_only_the_phases_it_has_steps_left_in():
    """Resumed at or past ``bbox_steps`` the phase-1 batch is never drawn again (only phase 2 is checked); resumed
    before it both are; at ``max_steps`` nothing is left to split."""
    for start in (10, 11, 99):
        check_world_split(bbox_steps=10, objects_phase1=3, objects_phase2=8, max_steps=100, world=8, start=start)
    with pytest.raises(DepthnerfError, match=r"^--schedule.objects_phase1 3: .* over 8 ranks"):
        check_world_split(bbox_steps=10, objects_phase1=3, objects_phase2=8, max_steps=100, world=8, start=9)
    with pytest.raises(DepthnerfError, match=r"^--schedule.objects_phase2 6: .* over 4 ranks; launch 1, 2, 3, 6 "):
        check_world_split(bbox_steps=10, objects_phase1=8, objects_phase2=6, max_steps=100, world=4, start=50)
    check_world_split(bbox_steps=10, objects_phase1=3, objects_phase2=6, max_steps=100, world=4, start=100)


def test_train_checks_the_split_from_the_step_it_resumes_at(tmp_path):
    """A run whose phase-1 batch (3) does not split over 2 ranks: refused as a new run, but its resume from the
    step-10 checkpoint (phase 1 ended at step 3) gets past the check (here to the next one: no process group)."""
    cfg = tiny_config("cars", "none")
    cfg = dataclasses.replace(cfg, schedule=dataclasses.replace(cfg.schedule, bbox_steps=3, objects_phase1=3,
                                                                objects_phase2=2, max_steps=20))
    info = DistInfo(rank=0, world=2, device=torch.device("cpu"))
    with pytest.raises(DepthnerfError, match=r"^--schedule.objects_phase1 3: .* over 2 ranks"):
        train(cfg, tmp_path / "new", info, progress=False)
    run = tiny_run(tmp_path / "run", cfg, steps=(5, 10), max_steps=20)
    with pytest.raises(Exception) as err:
        train(cfg, run, info, resume=True, progress=False)
    assert "does not split" not in str(err.value), err.value


def test_the_check_agrees_with_the_shard_that_a_step_takes():
    """Brute force: for every batch size and world size, the check passes exactly when ``shard`` can split."""
    for size in range(1, 13):
        for world in range(1, 13):
            try:
                check_world_split(bbox_steps=5, objects_phase1=size, objects_phase2=size, max_steps=10, world=world)
                ok = True
            except DepthnerfError:
                ok = False
            try:
                parts = [shard(list(range(size)), rank, world) for rank in range(world)]
                splits = sum(parts, []) == list(range(size))
            except ValueError:
                splits = False
            assert ok == splits, (size, world)


def test_train_refuses_before_reading_data(tmp_path):
    """The refusal comes before the data is read (here there is none), so a misfitted launch fails at once."""
    cfg = preset("paper-cars")
    with pytest.raises(DepthnerfError, match=r"does not split over 8 ranks"):
        train(cfg, tmp_path / "run", DistInfo(rank=0, world=8, device=torch.device("cpu")), progress=False)
