"""Where do two ``--deterministic`` training runs of the same seed part? Runs the exact-resume tests' tiny
configuration (``tests/test_train.py``'s ``CRASH_ARGS``: cpu-cars, ResNet18, 32 px, 6 steps) several times, first
one after another, then all at once (as pytest-xdist runs the tests on one GPU), with a checkpoint after every step,
and compares every run with the first: the first step whose logged loss terms differ, and for each checkpoint the
weights and optimiser tensors that differ (largest absolute difference). Writes OUT_DIR/determinism_probe.json
and prints a summary.

    python scripts/determinism_probe.py OUT_DIR [--sequential 3] [--concurrent 6] [--steps 6] [--device auto]
        [--work DIR] [--threads N]

On a CPU both groups should agree bit for bit (the CPU's default); on CUDA, ``--deterministic`` promises it.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import torch  # noqa: E402
from fixtures_checkpoints import TINY_TRAIN_FLAGS  # noqa: E402
from fixtures_srn import make_srn_fixture  # noqa: E402
from safetensors.torch import load_file  # noqa: E402

from depthnerf.train.run_log import read_metrics  # noqa: E402

TERMS = ("loss", "loss_coarse", "loss_fine", "loss_depth", "loss_background", "loss_foreground")


def train_command(data: Path, out: Path, steps: int, device: str) -> list[str]:
    return [sys.executable, "-m", "depthnerf", "train", "--preset", "cpu-cars", "--depth", "none", "--data",
            str(data), "--out", str(out), "--max-steps", str(steps), "--checkpoint-every", "1", "--log.val_every",
            "0", "--log.keep_last", str(steps + 1), "--deterministic", "--device", device, *TINY_TRAIN_FLAGS]


def run_group(cmds: list[list[str]], concurrent: bool, threads: int | None) -> list[dict]:
    """Run the commands all at once (``concurrent``) or one after another, with ``threads`` CPU threads each
    (``OMP_NUM_THREADS``; None: the environment's); each one's exit code, seconds, stderr."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if threads is not None:
        env.update(OMP_NUM_THREADS=str(threads), MKL_NUM_THREADS=str(threads))
    started, results = [], []

    def finish(t0: float, p: subprocess.Popen) -> dict:
        _, err = p.communicate()
        return {"returncode": p.returncode, "seconds": round(time.time() - t0, 1), "stderr": err[-800:]}

    for c in cmds:
        started.append((time.time(), subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                                      env=env)))
        if not concurrent:
            results.append(finish(*started.pop()))
    return results + [finish(*s) for s in started]


def checkpoint_tensors(run: Path, step: int) -> dict[str, torch.Tensor]:
    folder = run / "checkpoints" / f"step_{step:08d}"
    tensors = {f"model/{k}": v for k, v in load_file(folder / "model.safetensors").items()}
    tensors.update({f"optim/{k}": v for k, v in load_file(folder / "optimizer.safetensors").items()})
    return tensors


def compare(ref: Path, run: Path, steps: int) -> dict:
    a = {m["step"]: m for m in read_metrics(ref) if "loss" in m}
    b = {m["step"]: m for m in read_metrics(run) if "loss" in m}
    first_loss = next((s for s in sorted(a) if any(a[s][t] != b.get(s, {}).get(t) for t in TERMS)), None)
    terms_at_first = None if first_loss is None else {t: [a[first_loss][t], b[first_loss][t]] for t in TERMS}
    per_step = {}
    for step in range(1, steps + 1):
        ta, tb = checkpoint_tensors(ref, step), checkpoint_tensors(run, step)
        diff = {k: float((ta[k].double() - tb[k].double()).abs().max()) for k in ta if not torch.equal(ta[k], tb[k])}
        if diff:
            worst = sorted(diff.items(), key=lambda kv: -kv[1])
            per_step[step] = {"differing": len(diff), "of": len(ta), "largest": worst[:6],
                              "names": sorted(diff)[:40]}
    first_tensor = min(per_step, default=None)
    return {"first_differing_loss_step": first_loss, "terms_at_first": terms_at_first,
            "first_differing_checkpoint_step": first_tensor, "checkpoints": per_step}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--sequential", type=int, default=3)
    ap.add_argument("--concurrent", type=int, default=6)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a new temporary one)")
    ap.add_argument("--threads", type=int, default=None,
                    help="CPU threads per run (OMP_NUM_THREADS; default: the environment's)")
    args = ap.parse_args()
    if args.threads is not None and args.threads < 1:
        ap.error(f"--threads {args.threads}: give at least 1")
    args.out.mkdir(parents=True, exist_ok=True)
    work = args.work or Path(tempfile.mkdtemp(prefix="determinism-probe-"))
    data = make_srn_fixture(work / "srn", "cars", {"train": 4, "val": 1}, views=4, size=32, with_depth=True,
                            with_mask=True)
    report = {"cuda": torch.cuda.is_available(), "torch": torch.__version__,
              "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
              "threads": args.threads or torch.get_num_threads(),
              "groups": {}}
    runs = []
    for group, n, concurrent in (("sequential", args.sequential, False), ("concurrent", args.concurrent, True)):
        outs = [work / f"{group}_{i}" for i in range(n)]
        t0 = time.time()
        procs = run_group([train_command(data, o, args.steps, args.device) for o in outs], concurrent, args.threads)
        report["groups"][group] = {"seconds": round(time.time() - t0, 1), "processes": procs}
        runs += [(group, o) for o, p in zip(outs, procs, strict=True) if p["returncode"] == 0]
    if not runs:
        report["error"] = "no run finished"
    else:
        ref = runs[0][1]
        report["reference"] = ref.name
        report["comparisons"] = {o.name: compare(ref, o, args.steps) for _, o in runs[1:]}
    (args.out / "determinism_probe.json").write_text(json.dumps(report, indent=1))
    for name, c in report.get("comparisons", {}).items():
        print(f"{name}: first differing loss step {c['first_differing_loss_step']}, first differing checkpoint "
              f"{c['first_differing_checkpoint_step']}"
              + (f" ({c['checkpoints'][c['first_differing_checkpoint_step']]['largest'][:3]})"
                 if c["first_differing_checkpoint_step"] else ""))
    bad = [g for g, v in report["groups"].items() if any(p["returncode"] for p in v["processes"])]
    if bad:
        print(f"runs failed in: {bad}; see determinism_probe.json")


if __name__ == "__main__":
    main()
