"""Training: schedule pieces against closed forms, run folder contract, determinism, exact resume after SIGKILL,
the clean stop on SIGTERM / Ctrl+C (a checkpoint at that step, the resume command, exact resume), and DDP
(torchrun, gloo, 2 CPU processes) against a single process with the same global batch."""

from __future__ import annotations

import json
import math
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from fixtures_checkpoints import TINY_TRAIN_FLAGS as TINY
from fixtures_checkpoints import cli, final_weights, tiny_config, tiny_model
from fixtures_srn import make_srn_fixture

from depthnerf.config_io import apply_overrides, to_dict
from depthnerf.errors import DepthnerfError
from depthnerf.train import checkpoint as ckpt
from depthnerf.train.batching import BatchPlan, sample_pixels, step_keys
from depthnerf.train.config import check_config, preset, with_prior
from depthnerf.train.loop import learning_rate
from depthnerf.train.run_log import read_launches, read_metrics
from depthnerf.train.step import background_opacity_per_object, foreground_opacity_per_object


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


def test_exponential_learning_rate_counts_whole_epochs_exactly_at_their_boundaries():
    """Brute force: count the objects phase 2 has consumed step by step; the decay's exponent is how many whole
    epochs that is, also at the steps where an epoch ends exactly (where a difference of two fractional epochs
    rounds to just below the whole number: 7 objects, 4 per step, step 899 of cpu-cars)."""
    cfg = preset("cpu-cars")
    s = cfg.schedule
    for objects in (3, 7, 1200):
        plan = BatchPlan(num_objects=objects, seed=0, bbox_steps=s.bbox_steps, objects_phase1=s.objects_phase1,
                         objects_phase2=s.objects_phase2)
        consumed = 0
        for step in range(s.bbox_steps, s.bbox_steps + 3000):
            assert learning_rate(cfg, plan, step) == s.lr * s.lr_decay ** (consumed // objects), (objects, step)
            consumed += s.objects_phase2


def test_cosine_learning_rate_closed_form_and_its_bounds():
    cfg = apply_overrides(preset("cpu-chairs"), ["--schedule.lr_schedule", "cosine", "--schedule.lr_final", "1e-5"])
    s = cfg.schedule
    plan = BatchPlan(num_objects=8, seed=0, bbox_steps=s.bbox_steps, objects_phase1=s.objects_phase1,
                     objects_phase2=s.objects_phase2)
    mid = (s.bbox_steps + s.max_steps) // 2
    assert learning_rate(cfg, plan, 0) == s.lr == learning_rate(cfg, plan, s.bbox_steps)
    assert math.isclose(learning_rate(cfg, plan, mid), (s.lr + s.lr_final) / 2, rel_tol=1e-12)
    assert math.isclose(learning_rate(cfg, plan, s.max_steps), s.lr_final, rel_tol=1e-12)
    quarter = s.bbox_steps + (s.max_steps - s.bbox_steps) // 4
    assert math.isclose(learning_rate(cfg, plan, quarter),
                        s.lr_final + (s.lr - s.lr_final) * (2 + 2 ** 0.5) / 4, rel_tol=1e-12)
    rates = [learning_rate(cfg, plan, k) for k in range(s.max_steps + 1)]
    assert all(a >= b for a, b in zip(rates[:-1], rates[1:], strict=True))
    with pytest.raises(DepthnerfError, match="lr_final must be <="):
        check_config(apply_overrides(cfg, ["--schedule.lr_final", "1e-3"]))


def test_an_lr_decay_above_one_is_refused():
    cfg = preset("cpu-cars")
    assert check_config(apply_overrides(cfg, ["--schedule.lr_decay", "1"])).schedule.lr_decay == 1
    for bad in ("1.01", "nan"):
        with pytest.raises(DepthnerfError, match=r"--schedule\.lr_decay must be (in \(0, 1\]|> 0)"):
            check_config(apply_overrides(cfg, ["--schedule.lr_decay", bad]))


def test_baseline_and_depth_aware_presets_differ_only_in_the_prior_switch():
    base, depth = with_prior(preset("paper-cars"), "none"), with_prior(preset("paper-cars"), "bundled")
    assert not base.prior.enabled and depth.prior.enabled  # depth-awareness is derived from the prior, never stored
    assert base.model == depth.model and base.render == depth.render
    assert base.schedule == depth.schedule and base.data == depth.data


def test_checkpoint_refuses_other_model_config(tmp_path):
    model = torch.nn.Linear(2, 3)
    opt = torch.optim.Adam(model.parameters())
    saved = ckpt.save_checkpoint(tmp_path, model, opt, {"d": 1}, ckpt.TrainingState(5, 1.0))
    (tmp_path / ".step_00000009.123.tmp").mkdir()  # a write interrupted by a kill is never "latest"
    assert ckpt.latest_checkpoint(tmp_path) == saved
    state = json.loads((saved / "state.json").read_text())
    assert "extra" not in state
    (saved / "state.json").write_text(json.dumps({**state, "extra": {"old": 1}}))  # as older runs wrote it
    assert ckpt.load_checkpoint(saved, model, opt, {"d": 1}) == ckpt.TrainingState(5, 1.0)
    with pytest.raises(DepthnerfError, match="different model config"):
        ckpt.load_checkpoint(saved, torch.nn.Linear(2, 3), None, {"d": 2})
    with pytest.raises(DepthnerfError, match="shape mismatch"):
        ckpt.load_checkpoint(saved, torch.nn.Linear(2, 4), None, {"d": 1})


def test_checkpoint_from_before_a_new_model_field_resumes_with_its_default(tmp_path):
    """A run checkpointed before a model field existed (e.g. ``rgb_at_point``) resumes: the missing field takes its
    default, as inference reads it; a stored value that differs from the run's config is still refused."""
    cfg = tiny_config("cars", "none")
    model = tiny_model(cfg)
    opt = torch.optim.Adam(model.parameters())
    old = to_dict(cfg.model)
    del old["rgb_at_point"]
    saved = ckpt.save_checkpoint(tmp_path, model, opt, old, ckpt.TrainingState(3, 20.0))
    fresh = tiny_model(cfg, seed=1)
    assert ckpt.load_checkpoint(saved, fresh, torch.optim.Adam(fresh.parameters()), to_dict(cfg.model)).step == 3
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), fresh.state_dict().values(), strict=True))
    other = to_dict(apply_overrides(cfg, ["--model.prior_at_point", "true"]).model)
    with pytest.raises(DepthnerfError, match=r"different model config \(differs in: prior_at_point\)"):
        ckpt.load_checkpoint(saved, tiny_model(cfg), None, other)


# ---------------------------------------------------------------- end to end


def test_background_opacity_loss_closed_form():
    opacity = torch.tensor([[0.5, 1.0, 0.2], [0.3, 0.0, 0.9]])
    fg = torch.tensor([[True, False, False], [True, True, False]])
    per_object = background_opacity_per_object(opacity, fg)  # object 0: rays 1, 2; object 1: ray 2
    assert per_object.tolist() == pytest.approx([(1.0 + 0.04) / 2, 0.81])
    assert background_opacity_per_object(opacity, torch.ones_like(fg)).tolist() == [0.0, 0.0]  # no background ray


def test_foreground_opacity_loss_against_a_loop():
    """Per object, the mean of (1 - opacity)^2 over the object's rays, from a plain loop over random rays and
    masks (an object with no object ray gives 0)."""
    g = torch.Generator().manual_seed(3)
    opacity = torch.rand(4, 9, generator=g, dtype=torch.float64)
    fg = torch.rand(4, 9, generator=g) < 0.4
    fg[2] = False
    expected = []
    for b in range(4):
        values = [(1 - opacity[b, r].item()) ** 2 for r in range(9) if fg[b, r]]
        expected.append(sum(values) / len(values) if values else 0.0)
    assert foreground_opacity_per_object(opacity, fg).tolist() == pytest.approx(expected, abs=1e-12)
    assert foreground_opacity_per_object(torch.ones(2, 3), torch.ones(2, 3, dtype=torch.bool)).tolist() == [0, 0]


def test_background_opacity_term_enters_the_training_loss(data, tmp_path):
    """With ``--schedule.background_opacity_weight W`` the logged loss is coarse + fine + W * background (and the
    background term is logged, positive at initialisation, and logged unweighted at weight 0); on in the CPU
    presets, off in the paper's."""
    run = tmp_path / "bg"
    cli("train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--out", str(run),
        "--max-steps", "2", "--log.val_every", "0", "--schedule.background_opacity_weight", "0.5", *TINY)
    for m in (m for m in read_metrics(run) if "loss" in m):
        assert m["loss_background"] > 0
        assert m["loss"] == pytest.approx(m["loss_coarse"] + m["loss_fine"] + 0.5 * m["loss_background"], rel=1e-6)
    off = tmp_path / "off"
    cli("train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--out", str(off),
        "--max-steps", "2", "--log.val_every", "0", "--schedule.background_opacity_weight", "0", *TINY)
    for m in (m for m in read_metrics(off) if "loss" in m):
        assert m["loss_background"] > 0 and m["loss_foreground"] > 0
        assert m["loss"] == pytest.approx(m["loss_coarse"] + m["loss_fine"], rel=1e-6)
    fg = tmp_path / "fg"
    cli("train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--out", str(fg),
        "--max-steps", "2", "--log.val_every", "0", "--schedule.background_opacity_weight", "0",
        "--schedule.foreground_opacity_weight", "0.5", *TINY)
    for m in (m for m in read_metrics(fg) if "loss" in m):
        assert m["loss"] == pytest.approx(m["loss_coarse"] + m["loss_fine"] + 0.5 * m["loss_foreground"], rel=1e-6)
    assert preset("cpu-cars").schedule.background_opacity_weight == 0.02
    assert preset("cpu-chairs").schedule.background_opacity_weight == 0.02
    assert preset("paper-cars").schedule.background_opacity_weight == 0.0
    assert preset("paper-cars").schedule.foreground_opacity_weight == preset("cpu-cars").schedule.foreground_opacity_weight == 0


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


CRASH_ARGS = ["train", "--preset", "cpu-cars", "--depth", "none", "--max-steps", "6", "--checkpoint-every", "2",
              "--log.val_every", "0", "--log.keep_last", "1", *TINY,
              *(["--deterministic"] if torch.cuda.is_available() else [])]
"""Exact resume is the CPU's default and a ``--deterministic`` promise on CUDA (whose default kernels accumulate
gradients in a run-dependent order)."""


@pytest.fixture(scope="module")
def uninterrupted(data, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("full") / "run"
    cli(*CRASH_ARGS, "--data", str(data), "--out", str(run))
    return run


@pytest.mark.parametrize("stage", [s for s in ckpt.CRASH_STAGES if not s.startswith("best")])
def test_kill_at_every_stage_of_a_checkpoint_write_then_resume_is_exact(data, uninterrupted, tmp_path, stage):
    """SIGKILL (through the checkpoint writer's test hook) at each stage of the step-4 checkpoint write, then
    ``--resume``: the loss curve and the final weights equal the uninterrupted run's bit for bit."""
    run = tmp_path / "killed"
    killed = cli(*CRASH_ARGS, "--data", str(data), "--out", str(run), check=False,
                 env={"DEPTHNERF_CRASH_AT": f"{stage}@4"})
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    done = ckpt.latest_checkpoint(run / "checkpoints")
    expected = 2 if stage in ("weights", "optimizer", "state") else 4  # the step-4 folder is complete once renamed
    assert done is not None and done.name == f"step_{expected:08d}"
    resumed = cli(*CRASH_ARGS, "--data", str(data), "--out", str(run), "--resume")
    assert f"resumed from step {expected} (" in resumed.stderr
    assert losses(run) == losses(uninterrupted)
    assert sorted(losses(run)) == list(range(1, 7))
    ref = final_weights(uninterrupted)
    got = final_weights(run)
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)


def stop_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.startswith("stopped by ")]
    assert len(lines) == 1, stderr[-2000:]
    return lines[0]


def test_sigterm_mid_run_checkpoints_that_step_and_prints_the_resume_command(data, tmp_path):
    """A real SIGTERM from outside, at whatever step the run has reached: exit 143, a checkpoint at the last
    completed step, one line naming the command that resumes it, and that command resumes from that step."""
    run = tmp_path / "preempted"
    args = [*CRASH_ARGS, "--data", str(data), "--out", str(run)]
    args[args.index("--max-steps") + 1] = "500"  # far more than it reaches before the signal
    proc = subprocess.Popen([sys.executable, "-m", "depthnerf", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while max(losses(run), default=0) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err[-2000:]
    line = stop_line(err)
    step = max(losses(run))  # every step is logged (--log.log_every 1): the last one is where it stopped
    assert 2 <= step < 500 and line.startswith(f"stopped by SIGTERM at step {step}: checkpoint ")
    assert ckpt.latest_checkpoint(run / "checkpoints").name == f"step_{step:08d}"
    assert json.loads(out.strip().splitlines()[-1])["stopped_by"] == "SIGTERM"
    command = line.split("resume with: ", 1)[1]
    kept = ["--deterministic"] if torch.cuda.is_available() else []  # CRASH_ARGS' flag, not part of the config
    assert shlex.split(command) == ["depthnerf", "train", "--out", str(run.resolve()), "--resume", *kept,
                                    "--no-progress"]
    resumed = cli(*shlex.split(command)[1:], "--max-steps", str(step + 1))
    assert f"resumed from step {step} (" in resumed.stderr and max(losses(run)) == step + 1
    assert [(x["start_step"], x["world_size"]) for x in read_launches(run)] == [(0, 1), (step, 1)]


@pytest.mark.parametrize("hook, code, expected", [("sigterm-step@3", 143, 3), ("sigint-validation@4", 130, 4),
                                                  ("sigterm-weights@4", 143, 4)])
def test_stop_signal_then_resume_is_exact(data, uninterrupted, tmp_path, hook, code, expected):
    """SIGTERM after step 3 (between checkpoints), Ctrl+C as the step-4 validation starts (the validation is
    abandoned), SIGTERM in the middle of the step-4 checkpoint write (it completes, nothing more is written):
    the checkpoint is of that step, and ``--resume`` reproduces the uninterrupted run bit for bit."""
    run = tmp_path / "stopped"
    val = ["--log.val_every", "4"] if "validation" in hook else []
    stopped = cli(*CRASH_ARGS, "--data", str(data), "--out", str(run), *val, check=False,
                  env={"DEPTHNERF_CRASH_AT": hook})
    assert stopped.returncode == code, stopped.stderr[-2000:]
    assert stop_line(stopped.stderr).startswith(f"stopped by {'SIGINT' if code == 130 else 'SIGTERM'} at step "
                                                f"{expected}: ")
    assert ckpt.latest_checkpoint(run / "checkpoints").name == f"step_{expected:08d}"
    assert sorted(losses(run)) == list(range(1, expected + 1))
    assert not any("val_psnr" in m for m in read_metrics(run))
    cli(*CRASH_ARGS, "--data", str(data), "--out", str(run), "--resume", *val)
    assert losses(run) == losses(uninterrupted)
    ref, got = final_weights(uninterrupted), final_weights(run)
    assert ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)


def test_compile_flag_trains_and_its_resume_command_keeps_it(data, tmp_path):
    """``--compile`` trains (inductor on the CPU here) and, not being part of the run's config, is named in the
    command that resumes a stopped run."""
    run = tmp_path / "compiled"
    stopped = cli(*CRASH_ARGS, "--data", str(data), "--out", str(run), "--compile", check=False,
                  env={"DEPTHNERF_CRASH_AT": "sigterm-step@2"})
    assert stopped.returncode == 143, stopped.stderr[-2000:]
    assert sorted(losses(run)) == [1, 2] and all(math.isfinite(v) for v in losses(run).values())
    assert "--compile" in shlex.split(stop_line(stopped.stderr).split("resume with: ", 1)[1])


def test_warm_start_takes_the_source_weights_once_and_refuses_another_network(data, uninterrupted, tmp_path):
    source = ckpt.latest_checkpoint(uninterrupted / "checkpoints") / "model.safetensors"
    warm = tmp_path / "warm"
    args = [a for a in CRASH_ARGS if a != "--deterministic"]
    args[args.index("--max-steps") + 1] = "1"
    proc = cli(*args, "--data", str(data), "--out", str(warm), "--init-from", str(uninterrupted),
               "--schedule.lr", "1e-12")
    assert "warm start" in proc.stderr
    record = json.loads((warm / "init_from.json").read_text())
    assert record["path"] == str(source.resolve()) and record["step"] == 6 and record["total_steps"] == 6
    assert json.loads((warm / "config.json").read_text())["init_from"] == str(uninterrupted)
    before, after = ckpt.read_weights(source)[0], final_weights(warm)
    params = [k for k in before if "running_" not in k and "num_batches" not in k]
    assert params and all(torch.allclose(after[k], before[k], rtol=0, atol=1e-9) for k in params)  # one 1e-12 step
    fresh = tmp_path / "fresh"
    cli(*args, "--data", str(data), "--out", str(fresh), "--schedule.lr", "1e-12")
    assert not (fresh / "init_from.json").exists()
    assert max((final_weights(fresh)[k] - before[k]).abs().max().item() for k in params) > 1e-3
    resumed = cli("train", "--out", str(warm), "--resume", "--max-steps", "2", "--no-progress")
    assert "warm start" not in resumed.stderr and "resumed from step 1" in resumed.stderr
    wide = cli(*args, "--data", str(data), "--out", str(tmp_path / "wide"), "--init-from", str(source),
               "--model.fine.d_hidden", "48", check=False)
    assert wide.returncode == 2 and "model.fine.d_hidden = 32, the run 48" in wide.stderr
    assert str(source) in wide.stderr and not (tmp_path / "wide" / "checkpoints").exists()
    glob = cli(*args, "--data", str(data), "--out", str(tmp_path / "glob"), "--init-from", str(source),
               "--model.global_features", "true", "--schedule.lr", "1e-12")  # an added term starts at zero
    grown = final_weights(tmp_path / "glob")
    assert "warm start" in glob.stderr and all(torch.allclose(grown[k], before[k], rtol=0, atol=1e-9) for k in params)
    assert [k for k in grown if "lin_global" in k] and all(
        grown[k].abs().max() < 1e-9 for k in grown if "lin_global" in k)
    depth = cli(*[a if a != "none" else "oracle" for a in args], "--data", str(data), "--out", str(tmp_path / "d"),
                "--init-from", str(source), check=False)
    assert depth.returncode == 2 and "the run is depth-aware" in depth.stderr
    missing = cli(*args, "--data", str(data), "--out", str(tmp_path / "m"), "--init-from", str(tmp_path / "nope"),
                  check=False)
    assert missing.returncode == 2 and "nope" in missing.stderr


def test_resume_says_what_it_did_and_refuses_contradicting_flags(data, tmp_path, monkeypatch):
    run = tmp_path / "r"
    base = ["train", "--preset", "cpu-cars", "--depth", "none", "--log.val_every", "0", *TINY]
    started = cli(*base, "--data", str(data), "--out", str(run), "--max-steps", "2", "--resume")
    assert f"started a new run in {run} (no checkpoint found)" in started.stderr
    assert json.loads(started.stdout.strip().splitlines()[-1])["best_val_psnr"] is None  # strict JSON, no -Infinity
    refused = cli(*base, "--data", str(data), "--out", str(run), "--max-steps", "3", "--resume", "--depth",
                  "bundled", check=False)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1
    assert "contradict" in refused.stderr and "prior.estimator" in refused.stderr
    other = cli(*base, "--data", str(data), "--out", str(run), "--max-steps", "3", "--resume",
                "--schedule.lr", "0.5", check=False)
    assert other.returncode == 2 and "schedule.lr" in other.stderr
    resumed = cli(*base, "--data", str(data), "--out", str(run), "--max-steps", "3", "--resume")
    assert f"resumed from step 2 ({run / 'checkpoints' / 'step_00000002'})" in resumed.stderr
    same = cli("train", "--out", str(run), "--resume", "--max-steps", "2")  # below the run's step: said, not silent
    assert "nothing to train: the run is at step 3, --max-steps is 2 (pass a larger --max-steps" in same.stderr
    result = json.loads(same.stdout.strip().splitlines()[-1])  # the run's own checkpoint, not null
    assert result["step"] == 3 and result["checkpoint"] == str(run / "checkpoints" / "step_00000003")


def test_relative_data_run_resumes_from_another_directory(data, tmp_path):
    """A run started with a relative --data stores the resolved path; an explicit --data on resume wins (moved
    data), and stderr says so."""
    run = tmp_path / "rel"
    args = ["train", "--preset", "cpu-cars", "--depth", "none", "--log.val_every", "0", *TINY]
    proc = subprocess.run([sys.executable, "-m", "depthnerf", *args, "--data", data.name, "--out", str(run),
                           "--max-steps", "2"], cwd=data.parent, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((run / "config.json").read_text())["data"]["root"] == str(data.resolve())
    moved = tmp_path / "moved_data"
    shutil.copytree(data, moved)
    config = json.loads((run / "config.json").read_text())
    config["data"]["root"] = data.name  # as runs written before paths were stored resolved
    (run / "config.json").write_text(json.dumps(config))
    again = cli(*args, "--data", str(moved), "--out", str(run), "--max-steps", "3", "--resume")
    assert "resumed from step 2" in again.stderr and f"--data {moved}" in again.stderr
    assert losses(run).keys() == {1, 2, 3}


def test_deterministic_switch_runs_the_deterministic_kernels_and_agrees(data, tmp_path):
    """--deterministic (index-gather features, matmul resizing, deterministic algorithms) trains, repeats itself
    exactly, and agrees with the default kernels at the first step: up to float32 rounding on the CPU, up to one
    bf16 epsilon (2^-8) on CUDA, where training runs under bf16 autocast."""
    args = ["train", "--preset", "cpu-cars", "--depth", "oracle", "--data", str(data), "--max-steps", "2",
            "--log.val_every", "0", *TINY]
    det = [tmp_path / "d1", tmp_path / "d2"]
    for run in det:
        cli(*args, "--out", str(run), "--deterministic")
    cli(*args, "--out", str(tmp_path / "plain"))
    assert losses(det[0]) == losses(det[1])
    rel = 2.0**-8 if torch.cuda.is_available() else 1e-5
    assert losses(det[0])[1] == pytest.approx(losses(tmp_path / "plain")[1], rel=rel)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_device_cuda_without_a_gpu_is_one_line(data, tmp_path):
    proc = cli("train", "--preset", "cpu-cars", "--data", str(data), "--out", str(tmp_path / "x"),
               "--device", "cuda", *TINY, check=False)
    assert proc.returncode == 2 and proc.stderr.startswith("error: --device cuda: no CUDA GPU")
    assert proc.stderr.count("\n") == 1


@pytest.mark.slow
def test_torchrun_two_processes_match_one_process(data, tmp_path):
    """DDP's gradient averaging against one process. Both run the per-object step shape, so each object's
    arithmetic is the same in both and only the reduction differs; Adam turns the last-bit differences of other
    matmul shapes into 1e-4-level loss differences within 2 steps (with the CPU presets' background term: up to
    1.3e-4 relative at step 3). The batched step's rank split is checked on
    gradients in tests/test_train_step.py."""
    args = ["train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--max-steps", "3",
            "--log.val_every", "0", "--device", "cpu", "--schedule.step_shape", "per-object", *TINY]
    single = tmp_path / "single"
    cli(*args, "--out", str(single))
    ddp = tmp_path / "ddp"
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           "-m", "depthnerf", *args, "--out", str(ddp)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    ddp_losses, single_losses = losses(ddp), losses(single)
    assert ddp_losses[1] == pytest.approx(single_losses[1], rel=1e-5)  # before any update: rounding only
    assert ddp_losses == pytest.approx(single_losses, rel=5e-4)  # after 2 Adam steps: measured up to 1.3e-4
    assert [x["world_size"] for x in read_launches(ddp)] == [2] and read_launches(single)[0]["world_size"] == 1
    w_single, w_ddp = final_weights(single), final_weights(ddp)
    for key, value in w_single.items():
        if "running_" in key or "num_batches" in key:
            continue  # BatchNorm running statistics are rank 0's own (DDP broadcasts buffers from rank 0)
        # Adam's step is ~lr * sign(gradient) where a gradient is near 0, so a last-bit difference can flip one
        # step: |difference| <= 2 * lr per step
        bound = 2 * preset("cpu-cars").schedule.lr * 3
        assert torch.allclose(value.float(), w_ddp[key].float(), rtol=1e-3, atol=bound), key
