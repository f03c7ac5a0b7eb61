"""Checkpoint files (depthnerf.train.checkpoint) without a training run: what a save and a load must give back,
pruning, re-saving a step, and the resume's mending of ``best/``."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import torch

from depthnerf.train import checkpoint as ckpt


class _CountingSGD(torch.optim.SGD):
    """SGD with momentum that also keeps a plain-number count per parameter (state that is not a tensor)."""

    def step(self, closure=None):
        out = super().step(closure)
        for group in self.param_groups:
            for p in group["params"]:
                self.state[p]["calls"] = self.state[p].get("calls", 0) + 1
        return out


def _trained(seed: int, steps: int = 3) -> tuple[torch.nn.Module, torch.optim.Optimizer]:
    torch.manual_seed(seed)
    model = torch.nn.Linear(3, 2)
    opt = _CountingSGD(model.parameters(), lr=0.1, momentum=0.9)
    for _ in range(steps):
        opt.zero_grad()
        model(torch.randn(4, 3)).pow(2).sum().backward()
        opt.step()
    return model, opt


def _save(root: Path, step: int, seed: int = 0, **state) -> Path:
    model, opt = _trained(seed)
    fields = {"best_psnr": 12.5, **state}
    return ckpt.save_checkpoint(root, model, opt, {"toy": 1}, ckpt.TrainingState(step=step, **fields), keep_last=2)


def test_save_then_load_gives_back_weights_optimizer_and_state(tmp_path):
    model, opt = _trained(0)
    state = ckpt.TrainingState(step=7, best_psnr=21.25, world_size=2, best_step=5)
    saved = ckpt.save_checkpoint(tmp_path, model, opt, {"toy": 1}, state)
    fresh = torch.nn.Linear(3, 2)
    fresh_opt = _CountingSGD(fresh.parameters(), lr=0.5, momentum=0.1)
    assert ckpt.load_checkpoint(saved, fresh, fresh_opt, {"toy": 1}) == state
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), fresh.state_dict().values(),
                                                   strict=True))
    for p, q in zip(model.parameters(), fresh.parameters(), strict=True):
        assert fresh_opt.state[q]["calls"] == 3 and torch.equal(fresh_opt.state[q]["momentum_buffer"],
                                                                 opt.state[p]["momentum_buffer"])
    assert fresh_opt.param_groups[0]["lr"] == 0.1 and fresh_opt.param_groups[0]["momentum"] == 0.9
    no_validation = ckpt.TrainingState(step=8, best_psnr=-math.inf)
    unvalidated = ckpt.save_checkpoint(tmp_path, model, opt, {"toy": 1}, no_validation)
    assert json.loads((unvalidated / "state.json").read_text())["best_psnr"] is None  # strict JSON
    assert ckpt.load_checkpoint(unvalidated, fresh, None, {"toy": 1}) == no_validation


def test_pruning_keeps_the_newest_and_a_step_saved_again_is_replaced(tmp_path):
    for step in (1, 2, 3):
        _save(tmp_path, step)
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_00000002", "step_00000003"]  # keep_last=2
    again = _save(tmp_path, 3, seed=1)
    fresh = torch.nn.Linear(3, 2)
    ckpt.load_checkpoint(again, fresh, None, {"toy": 1})
    assert torch.equal(fresh.weight, _trained(1)[0].weight)
    assert (tmp_path / "latest").read_text() == "step_00000003\n"


def test_pruning_counts_only_complete_checkpoints_and_removes_half_deleted_folders(tmp_path):
    """Step folders an earlier kill left half-deleted (a newer one without its optimizer and state, an empty older
    one) are not counted among the ``keep_last`` kept: the two newest complete checkpoints stay; a leftover goes
    with the steps older than those."""
    for step in (1, 2):
        _save(tmp_path, step)
    half = tmp_path / "step_00000003"
    shutil.copytree(tmp_path / "step_00000002", half)
    for name in ("optimizer.safetensors", "state.json"):
        (half / name).unlink()
    (tmp_path / "step_00000000").mkdir()
    _save(tmp_path, 4)  # keep_last=2
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_00000002", "step_00000003", "step_00000004"]
    _save(tmp_path, 5)
    assert sorted(p.name for p in tmp_path.glob("step_*")) == ["step_00000004", "step_00000005"]


def test_a_kill_while_pruning_leaves_no_half_deleted_step_folder(tmp_path, monkeypatch):
    """A pruned folder is renamed away before it is deleted: a kill in the middle of the deletion (here: after its
    first file) leaves only a temporary name, which the resume removes; every step folder left is complete."""
    for step in (1, 2):
        _save(tmp_path, step)
    delete = shutil.rmtree

    def killed_midway(path, *args, **kwargs):
        files = sorted(Path(path).glob("*.safetensors")) if Path(path).is_dir() else []
        if not files:
            return delete(path, *args, **kwargs)
        files[0].unlink()
        raise KeyboardInterrupt  # stands for the kill: nothing after it runs

    monkeypatch.setattr(shutil, "rmtree", killed_midway)
    try:
        _save(tmp_path, 3)
    except KeyboardInterrupt:
        pass
    monkeypatch.undo()
    assert all((p / "state.json").is_file() and (p / "model.safetensors").is_file() and
               (p / "optimizer.safetensors").is_file() for p in tmp_path.glob("step_*"))
    ckpt.restore_best(tmp_path, ckpt.TrainingState(3, 12.5))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest", "step_00000002", "step_00000003"]


def test_resume_mends_best_only_when_it_holds_another_step(tmp_path):
    """``best/`` holding the recorded best step is left alone (no copy, no note); holding another step, or missing,
    it becomes a copy of the best step's folder; stray temporary folders of killed writers are removed."""
    first = _save(tmp_path, 1)
    ckpt.mark_best(tmp_path, first)
    _save(tmp_path, 2, best_step=2)
    marker = tmp_path / "best" / "kept.txt"
    marker.write_text("untouched")
    assert ckpt.restore_best(tmp_path, ckpt.TrainingState(2, 12.5, best_step=1)) is None
    assert marker.is_file()
    strays = [tmp_path / ".step_00000003.99.tmp", tmp_path / ".best.99.tmp"]
    for stray in strays:
        stray.mkdir()
    note = ckpt.restore_best(tmp_path, ckpt.TrainingState(2, 12.5, best_step=2))
    assert note == f"restored {tmp_path / 'best'} from step_00000002 (a kill had interrupted its copy)"
    assert json.loads((tmp_path / "best" / "state.json").read_text())["step"] == 2 and not marker.exists()
    assert not any(stray.exists() for stray in strays)
    assert ckpt.restore_best(tmp_path, ckpt.TrainingState(2, 12.5, best_step=2)) is None


def test_a_best_copy_after_a_kill_that_left_its_old_folder_replaces_best(tmp_path):
    """A kill after ``best/`` took its new copy but before the old one was removed leaves ``.best.PID.old`` (the
    resume finds ``best/`` complete and leaves it); a later process with the same process id (a container's
    training process usually has one) must still replace ``best/``, not fail on the stale folder."""
    first = _save(tmp_path, 1)
    ckpt.mark_best(tmp_path, first)
    stale = tmp_path / f".best.{os.getpid()}.old"
    shutil.copytree(first, stale)  # what the killed process left, under this process's id
    assert ckpt.restore_best(tmp_path, ckpt.TrainingState(1, 12.5, best_step=1)) is None
    second = _save(tmp_path, 2, best_step=2)
    ckpt.mark_best(tmp_path, second)
    assert json.loads((tmp_path / "best" / "state.json").read_text())["step"] == 2
    assert not stale.exists()


def _adam_steps(model: torch.nn.Module, opt: torch.optim.Optimizer, steps: int) -> None:
    torch.manual_seed(5)
    for _ in range(steps):
        opt.zero_grad()
        model(torch.randn(4, 3)).pow(2).sum().backward()
        opt.step()


def test_a_resume_on_another_device_keeps_its_own_fused_adam_setting(tmp_path):
    """A checkpoint of a CUDA run records fused Adam (``"fused": true``, crafted here into a CPU checkpoint's
    ``state.json``): a CPU resume keeps the setting it built its optimizer with (how the update runs on this device,
    not what it computes), and its next steps equal those of a resume from the CPU checkpoint itself."""
    torch.manual_seed(0)
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters(), lr=0.01)
    _adam_steps(model, opt, 2)
    saved = ckpt.save_checkpoint(tmp_path / "cpu", model, opt, {"toy": 1}, ckpt.TrainingState(2, 12.5))
    cuda = shutil.copytree(saved, tmp_path / "cuda" / saved.name)
    state = json.loads((cuda / "state.json").read_text())
    for group in state["optimizer"]["param_groups"]:
        group["fused"] = True
    (cuda / "state.json").write_text(json.dumps(state))
    weights = []
    for folder in (saved, cuda):
        fresh = torch.nn.Linear(3, 2)
        fresh_opt = torch.optim.Adam(fresh.parameters(), lr=0.01, fused=None)
        ckpt.load_checkpoint(folder, fresh, fresh_opt, {"toy": 1})
        assert [g["fused"] for g in fresh_opt.param_groups] == [None]
        _adam_steps(fresh, fresh_opt, 2)
        weights.append(fresh.state_dict())
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
