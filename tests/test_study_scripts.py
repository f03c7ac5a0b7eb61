"""The study shell scripts hand ``depthnerf`` the flags their docs promise: run with a stand-in ``depthnerf`` on
PATH that records each call, so the scripts' control flow runs in full without training anything."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parent.parent / "scripts"


@pytest.fixture
def recorder(tmp_path):
    """A ``depthnerf`` that appends its arguments to ``calls.txt`` and succeeds; PATH and the log for a script."""
    if shutil.which("bash") is None:
        pytest.skip("no bash")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "depthnerf"
    fake.write_text('#!/usr/bin/env bash\necho "$*" >> "$CALLS"\n')
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    calls = tmp_path / "calls.txt"
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ['PATH']}", "CALLS": str(calls)}
    return env, calls


def _train_calls(calls: Path) -> list[list[str]]:
    return [line.split() for line in calls.read_text().splitlines() if line.startswith("train ")]


def _flag(args: list[str], name: str) -> str:
    values = [args[i + 1] for i, a in enumerate(args) if a == name]
    assert len(values) == 1, f"{name} given {len(values)} times in {' '.join(args)}"
    return values[0]


def test_recipe_sets_the_documented_anneal_flags():
    out = subprocess.run(["bash", "-c", f'source {SCRIPTS / "anneal_recipe.sh"}; anneal_flags RUN 1e-4; '
                                        'echo "$ANNEAL_SEED ${ANNEAL_FLAGS[*]}"'],
                         capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == "1"
    flags = out[1:]
    assert _flag(flags, "--init-from") == "RUN" and _flag(flags, "--schedule.lr") == "1e-4"
    assert _flag(flags, "--schedule.lr_final") == "3e-6" and _flag(flags, "--schedule.lr_schedule") == "cosine"
    assert _flag(flags, "--schedule.bbox_steps") == "0" and _flag(flags, "--log.val_every") == "0"


def test_run_study_anneal_variant_trains_its_start_then_anneals_it(recorder, tmp_path):
    env, calls = recorder
    study = tmp_path / "study"
    env.update(RUNS="cars-bundled-an", CATEGORIES="cars", JOBS="1", ANNEAL_STEPS="300")
    done = subprocess.run(["bash", str(SCRIPTS / "run_study.sh"), str(study)], env=env, capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr
    start, annealed = _train_calls(calls)
    assert _flag(start, "--out") == f"{study}/runs/cars-bundled" and _flag(start, "--seed") == "0"
    assert "--init-from" not in start
    assert _flag(annealed, "--out") == f"{study}/runs/cars-bundled-an"
    assert _flag(annealed, "--init-from") == f"{study}/runs/cars-bundled"
    assert _flag(annealed, "--seed") == "1" and _flag(annealed, "--max-steps") == "300"
    assert _flag(annealed, "--schedule.lr_schedule") == "cosine" and _flag(annealed, "--schedule.lr_final") == "3e-6"
    assert _flag(annealed, "--depth") == "bundled" and _flag(annealed, "--preset") == "cpu-cars"


def test_run_study_variants_add_their_model_flags(recorder, tmp_path):
    env, calls = recorder
    env.update(RUNS="chairs-bundled-sym-pp-gf-s1", CATEGORIES="chairs", JOBS="1")
    done = subprocess.run(["bash", str(SCRIPTS / "run_study.sh"), str(tmp_path / "study")], env=env,
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    (args,) = _train_calls(calls)
    assert _flag(args, "--model.mirror") == "true" and _flag(args, "--model.prior_at_point") == "true"
    assert _flag(args, "--model.global_features") == "true" and _flag(args, "--seed") == "1"
    assert "--model.rgb_at_point" not in args


def test_run_study_rejects_an_unknown_variant(recorder, tmp_path):
    env, calls = recorder
    env.update(RUNS="cars-bundled-zz", CATEGORIES="cars", JOBS="1")
    done = subprocess.run(["bash", str(SCRIPTS / "run_study.sh"), str(tmp_path / "study")], env=env,
                          capture_output=True, text=True)
    assert done.returncode != 0 and "unknown run variant 'zz' in cars-bundled-zz" in done.stderr
    assert not _train_calls(calls)


def test_reanneal_study_continues_the_shipped_model_at_two_rates_and_scores_both_seeds(recorder, tmp_path):
    env, calls = recorder
    fake_python = Path(env["PATH"].split(os.pathsep)[0]) / "python"
    fake_python.write_text('#!/usr/bin/env bash\necho "python $*" >> "$CALLS"\n')
    fake_python.chmod(fake_python.stat().st_mode | stat.S_IEXEC)
    out = tmp_path / "re"
    done = subprocess.run(["bash", str(SCRIPTS / "reanneal_study.sh"), str(out)], env=env, capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr
    lines = calls.read_text().splitlines()
    synth = [line.split() for line in lines if line.startswith("synth ")]
    assert [_flag(a, "--seed") for a in synth] == ["0", "4242"]
    assert _flag(synth[0], "--train-objects") == "300" and _flag(synth[0], "--test-objects") == "50"
    trains = sorted(_train_calls(calls), key=lambda a: _flag(a, "--schedule.lr"))
    assert [_flag(a, "--schedule.lr") for a in trains] == ["1e-4", "3e-4"]
    assert [_flag(a, "--schedule.lr_final") for a in trains] == ["1e-6", "3e-6"]
    for args in trains:
        assert _flag(args, "--init-from") == "cpu-cars-sym-pp" and _flag(args, "--seed") == "2"
        assert _flag(args, "--max-steps") == "3000" and _flag(args, "--model.mirror") == "true"
        assert _flag(args, "--model.prior_at_point") == "true" and _flag(args, "--depth-checkpoint") == "srn"
    evals = [line.split() for line in lines if line.startswith("eval ")]
    assert sorted(_flag(a, "--out") for a in evals) == sorted(
        f"{out}/{where}/{name}" for where in ("eval", "eval-unseen") for name in ("shipped", "lr3e-4", "lr1e-4"))
    assert sum(line.startswith("python ") and "paired_difference.py" in line for line in lines) == 2
