"""Training: schedule pieces against closed forms, run folder contract, determinism, exact resume after SIGKILL,
and DDP (torchrun, gloo, 2 CPU processes) against a single process with the same global batch."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from fixtures_srn import make_srn_fixture

from depthnerf.errors import DepthnerfError
from depthnerf.train import checkpoint as ckpt
from depthnerf.train.batching import BatchPlan, sample_pixels, step_keys
from depthnerf.train.config import preset, with_prior
from depthnerf.train.loop import background_opacity_loss, learning_rate
from depthnerf.train.run_log import read_metrics

TINY = ["--data.resolution", "32", "--data.num_workers", "0", "--model.encoder.backbone", "resnet18",
        "--model.coarse.d_hidden", "32", "--model.fine.d_hidden", "32", "--render.sampler.n_coarse", "8",
        "--render.sampler.n_importance", "4", "--render.sampler.n_gaussian", "4", "--schedule.bbox_steps", "3",
        "--schedule.objects_phase1", "2", "--schedule.objects_phase2", "2", "--schedule.rays_per_object", "32",
        "--log.log_every", "1", "--no-progress"]


def cli(*args: str, check: bool = True, env: dict | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "depthnerf", *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})})
    if check and proc.returncode != 0:
        raise AssertionError(f"depthnerf {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return proc


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("srn")
    return make_srn_fixture(root, "cars", {"train": 4, "val": 1}, views=4, size=32, with_depth=True, with_mask=True)


def losses(run: Path) -> dict[int, float]:
    return {m["step"]: m["loss"] for m in read_metrics(run) if "loss" in m}


# ---------------------------------------------------------------- schedule pieces


def test_batch_plan_draws_every_object_once_per_epoch():
    plan = BatchPlan(num_objects=10, seed=3, bbox_steps=2, objects_phase1=4, objects_phase2=6)
    drawn = [o for s in range(4) for o in plan.objects(s)]  # 4 + 4 + 6 + 6 = 20 = two epochs
    assert sorted(drawn[:10]) == list(range(10)) and sorted(drawn[10:]) == list(range(10))
    assert plan.consumed(3) == 4 + 4 + 6 and plan.batch_size(1) == 4 and plan.batch_size(2) == 6


def test_step_keys_shard_the_global_batch():
    plan = BatchPlan(num_objects=7, seed=0, bbox_steps=5, objects_phase1=4, objects_phase2=4)
    whole = step_keys(plan, 3, 0, 1)
    assert step_keys(plan, 3, 0, 2) + step_keys(plan, 3, 1, 2) == whole
    with pytest.raises(ValueError):
        step_keys(plan, 3, 0, 3)


def test_bbox_pixels_stay_in_the_box():
    gen = torch.Generator().manual_seed(0)
    boxes = torch.tensor([[3, 5, 10, 7], [0, 0, 0, 0]])
    view, row, col = sample_pixels(2000, (2, 16, 16), boxes, gen)
    b = boxes[view]
    assert ((col >= b[:, 0]) & (col <= b[:, 2]) & (row >= b[:, 1]) & (row <= b[:, 3])).all()
    assert set(col[view == 0].tolist()) == set(range(3, 11))  # every column of the box is reachable


def test_learning_rate_schedule_closed_form():
    cfg = preset("cpu-cars")
    s = cfg.schedule
    plan = BatchPlan(num_objects=8, seed=0, bbox_steps=s.bbox_steps, objects_phase1=s.objects_phase1,
                     objects_phase2=s.objects_phase2)
    assert learning_rate(cfg, plan, 0) == s.lr == learning_rate(cfg, plan, s.bbox_steps)
    steps_per_epoch = 8 / s.objects_phase2
    step = s.bbox_steps + int(5 * steps_per_epoch)
    assert math.isclose(learning_rate(cfg, plan, step), s.lr * s.lr_decay ** 5)


def test_baseline_and_depth_aware_presets_differ_only_in_the_prior_switch():
    base, depth = with_prior(preset("paper-cars"), "none"), with_prior(preset("paper-cars"), "bundled")
    assert not base.prior.enabled and depth.prior.enabled  # use_depth is derived from the prior, never stored
    assert base.model == depth.model and base.render == depth.render
    assert base.schedule == depth.schedule and base.data == depth.data


def test_checkpoint_refuses_other_model_config(tmp_path):
    model = torch.nn.Linear(2, 3)
    opt = torch.optim.Adam(model.parameters())
    saved = ckpt.save_checkpoint(tmp_path, model, opt, {"d": 1}, ckpt.TrainingState(5, 1.0, {}))
    (tmp_path / ".step_00000009.123.tmp").mkdir()  # a write interrupted by a kill is never "latest"
    assert ckpt.latest_checkpoint(tmp_path) == saved
    with pytest.raises(DepthnerfError, match="different model config"):
        ckpt.load_checkpoint(saved, torch.nn.Linear(2, 3), None, {"d": 2})
    with pytest.raises(DepthnerfError, match="shape mismatch"):
        ckpt.load_checkpoint(saved, torch.nn.Linear(2, 4), None, {"d": 1})


# ---------------------------------------------------------------- end to end


def test_background_opacity_loss_closed_form():
    opacity = torch.tensor([[0.5, 1.0, 0.2], [0.3, 0.0, 0.9]])
    fg = torch.tensor([[True, False, False], [True, True, False]])
    assert float(background_opacity_loss(opacity, fg)) == pytest.approx((1.0 + 0.04 + 0.81) / 3)
    assert float(background_opacity_loss(opacity, torch.ones_like(fg))) == 0.0  # no background ray: no loss


def test_background_opacity_term_enters_the_training_loss(data, tmp_path):
    """With ``--schedule.background_opacity_weight W`` the logged loss is coarse + fine + W * background (and the
    background term is logged, positive at initialisation); off by default (logged as 0)."""
    run = tmp_path / "bg"
    cli("train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--out", str(run),
        "--max-steps", "2", "--log.val_every", "0", "--schedule.background_opacity_weight", "0.5", *TINY)
    for m in (m for m in read_metrics(run) if "loss" in m):
        assert m["loss_background"] > 0
        assert m["loss"] == pytest.approx(m["loss_coarse"] + m["loss_fine"] + 0.5 * m["loss_background"], rel=1e-6)
    assert preset("cpu-cars").schedule.background_opacity_weight == 0.0


def test_train_run_folder_determinism_and_refusal_to_overwrite(data, tmp_path):
    runs = []
    for name in ("a", "b"):
        run = tmp_path / name
        cli("train", "--preset", "cpu-cars", "--depth", "oracle", "--data", str(data), "--out", str(run),
            "--max-steps", "4", "--checkpoint-every", "2", "--log.val_every", "2", *TINY)
        runs.append(run)
    a = read_metrics(runs[0])
    assert {"step", "loss", "lr"} <= set(a[0]) and [m["step"] for m in a if "loss" in m] == [1, 2, 3, 4]
    assert any("val_psnr" in m for m in a)
    assert losses(runs[0]) == losses(runs[1])  # same seed + same data => same curve
    for name in ("config.json", "prior.json", "data_card.json"):
        assert (runs[0] / name).is_file()
    assert json.loads((runs[0] / "prior.json").read_text())["estimator"] == "oracle"
    assert list((runs[0] / "tb").glob("events.*"))
    assert (runs[0] / "checkpoints" / "best" / "model.safetensors").is_file()
    again = cli("train", "--preset", "cpu-cars", "--data", str(data), "--out", str(runs[0]), "--max-steps", "4",
                *TINY, check=False)
    assert again.returncode == 2 and "--resume" in again.stderr


def test_sigkill_then_resume_reproduces_the_uninterrupted_curve(data, tmp_path):
    args = ["train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--max-steps", "12",
            "--checkpoint-every", "3", "--log.val_every", "0", *TINY]
    full = tmp_path / "full"
    cli(*args, "--out", str(full))
    killed = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "depthnerf", *args, "--out", str(killed)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and not (killed / "checkpoints" / "step_00000006").is_dir():
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done = ckpt.latest_checkpoint(killed / "checkpoints")
    assert done is not None and 6 <= int(done.name.split("_")[1]) < 12, "kill landed outside the run"
    cli(*args, "--out", str(killed), "--resume")
    assert losses(killed) == pytest.approx(losses(full), rel=1e-6, abs=1e-9)
    assert sorted(losses(killed)) == list(range(1, 13))


@pytest.mark.slow
def test_torchrun_two_processes_match_one_process(data, tmp_path):
    args = ["train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--max-steps", "3",
            "--log.val_every", "0", "--device", "cpu", *TINY]
    single = tmp_path / "single"
    cli(*args, "--out", str(single))
    ddp = tmp_path / "ddp"
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           "-m", "depthnerf", *args, "--out", str(ddp)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert losses(ddp) == pytest.approx(losses(single), rel=1e-4)
    w_single = ckpt.read_weights(ckpt.latest_checkpoint(single / "checkpoints") / "model.safetensors")[0]
    w_ddp = ckpt.read_weights(ckpt.latest_checkpoint(ddp / "checkpoints") / "model.safetensors")[0]
    for key, value in w_single.items():
        if "running_" in key or "num_batches" in key:
            continue  # BatchNorm running statistics are rank 0's own (DDP broadcasts buffers from rank 0)
        assert torch.allclose(value.float(), w_ddp[key].float(), rtol=1e-3, atol=1e-5), key
