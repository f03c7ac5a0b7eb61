"""One-command GPU check (issue 19), run by ``scripts/gpu_check.sh OUT_DIR``; writes ``OUT_DIR/gpu_check.json``
(compact: device, settings, and per stage ``status`` ok / failed / skipped, ``seconds``, ``limit_s``,
``details``), ``OUT_DIR/gpu_check.log`` (every command and its output) and ``OUT_DIR/pytest_report.jsonl`` (one
line per test outcome). The JSON is rewritten after every stage, so a run stopped from outside keeps what it did.

Stages, in order (each in its own subprocesses under its own time limit; a failing stage never stops the next):

- ``env``: GPU name (nvidia-smi and torch), driver, torch / CUDA / cuDNN versions, Python, CPUs, packages.
- ``bench``: ``benchmarks/bench_gpu.py --json`` on CUDA (ms per iteration, kernel launches per step, peak memory,
  ms per 128x128 view with the paper sampler and guided, the 704 x 250-view eval projection), baseline with views,
  the same with ``--compile`` (training step and views), with ``--compile-step`` (the step as one compiled
  graph, CUDA graphs; no views), ``benchmarks/bench_view_variants.py`` (ms per view with a bf16 residual stream
  and with ``max-autotune`` compilation, against fp32 renders), depth-aware without views, and
  ``benchmarks/bench_gather.py`` (the feature gather's candidate kernels); on a CPU the aten op count (the launch
  proxy) and the CUDA figures as skipped.
- ``data``: a tiny synthetic car set made by ``depthnerf synth``.
- ``train``: side by side, paper preset with ``--deterministic``: run ``a`` (uninterrupted), ``c`` (``a``
  again, same seed), ``b`` (killed by ``DEPTHNERF_CRASH_AT`` at a checkpoint stage, then ``--resume``d); on
  CUDA also ``f1`` / ``f2`` (same seed, default fast kernels).
- ``resume_exact`` (a vs b) and ``same_seed`` (a vs c): every logged loss term of every step, the final weights
  and the optimiser state, bit for bit; ``fast_kernels`` (f1 vs f2, CUDA only): how far apart they are.
- ``pytest``: ``python -m pytest`` (pytest-xdist and pytest-timeout where installed) with the time that is left:
  tests that have not started by its deadline are skipped and counted, the failing test ids are listed.

Environment (defaults on CUDA / on a CPU): GPU_CHECK_DEVICE (auto; cpu hides CUDA), GPU_CHECK_STAGES (all),
GPU_CHECK_SECONDS (total budget: 450 / 900), GPU_CHECK_TIMEOUT_<STAGE> (seconds), GPU_CHECK_WORK (scratch:
/tmp/depthnerf-gpu-check, emptied first), GPU_CHECK_STEPS (200 / 6), GPU_CHECK_CKPT_EVERY (50 / 2),
GPU_CHECK_CRASH (state@<2 x CKPT_EVERY>), GPU_CHECK_RES (128 / 32), GPU_CHECK_OBJECTS (8 / 2), GPU_CHECK_VIEWS
(24 / 4), GPU_CHECK_PRESET (paper-cars), GPU_CHECK_DEPTH (oracle), GPU_CHECK_TRAIN_ARGS (extra train flags;
CPU: tiny model sizes), GPU_CHECK_PYTEST_ARGS (instead of the whole suite), GPU_CHECK_PYTEST_WORKERS,
GPU_CHECK_BENCH_CASES (CUDA: some of the bench stage's cases, e.g. ``compiled_step view_variants``; default all),
GPU_CHECK_VIEW_VARIANTS (the ``view_variants`` case's variants, e.g. ``compiled compiled+inside``; default all).
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from gpu_check_parts import (  # noqa: E402
    ROOT,
    Proc,
    bench_cases,
    env_probe_code,
    headline,
    pytest_summary,
    signal_group,
    source_digest,
    stop_group,
    train_plan,
)

STAGES = ("env", "bench", "data", "train", "resume_exact", "same_seed", "fast_kernels", "pytest")
CUDA_ONLY = {"fast_kernels"}
LIMITS = {"env": 60, "bench": 330, "data": 90, "train": 200, "resume_exact": 60, "same_seed": 60,
          "fast_kernels": 60, "pytest": 3600}


class Check:
    def __init__(self, out: Path) -> None:
        self.out = out
        self.t0 = time.time()
        self.py = os.environ.get("PY") or sys.executable
        self.forced_cpu = os.environ.get("GPU_CHECK_DEVICE", "auto") == "cpu"
        self.env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        if self.forced_cpu:
            self.env["CUDA_VISIBLE_DEVICES"] = ""
        self.cuda = False
        self.total = None
        self.work = Path(os.environ.get("GPU_CHECK_WORK", "/tmp/depthnerf-gpu-check"))
        shutil.rmtree(self.work, ignore_errors=True)
        self.work.mkdir(parents=True)
        selected = os.environ.get("GPU_CHECK_STAGES", " ".join(STAGES)).replace(",", " ").split()
        unknown = set(selected) - set(STAGES)
        if unknown:
            raise SystemExit(f"GPU_CHECK_STAGES: unknown stage(s) {sorted(unknown)}; stages: {' '.join(STAGES)}")
        self.selected = set(selected) | {"env"}
        self.logf = open(out / "gpu_check.log", "w")
        self.result: dict = {"schema": 1, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "finished": None,
                             "host": socket.gethostname(), "stages": {}}

    # ------------------------------------------------------------------ plumbing
    def log(self, text: str) -> None:
        self.logf.write(text.rstrip("\n") + "\n")
        self.logf.flush()

    def save(self) -> None:
        self.result["seconds"] = round(time.time() - self.t0, 1)
        self.result["summary"] = {k: v["status"] for k, v in self.result["stages"].items()}
        tmp = self.out / "gpu_check.json.tmp"
        tmp.write_text(json.dumps(self.result, indent=1) + "\n")
        os.replace(tmp, self.out / "gpu_check.json")

    def remaining(self) -> float:
        return (self.total or 3600) - (time.time() - self.t0)

    def run(self, cmd: list[str], timeout: float, env: dict | None = None, sig=signal.SIGTERM) -> Proc:
        """Run ``cmd`` in its own process group; on timeout send ``sig`` to the group, SIGKILL 15 s later."""
        self.log(f"$ {shlex.join(cmd)}  (limit {timeout:.0f} s)")
        t = time.time()
        proc = subprocess.Popen(cmd, cwd=ROOT, env={**self.env, **(env or {})}, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, errors="replace", start_new_session=True)
        try:
            out, _ = proc.communicate(timeout=max(1.0, timeout))
            timed_out = False
        except subprocess.TimeoutExpired:  # read while it stops: pytest prints its summary on SIGINT
            timed_out = True
            signal_group(proc, sig)
            try:
                out, _ = proc.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                signal_group(proc, signal.SIGKILL)
                out, _ = proc.communicate()
        result = Proc(proc.returncode, out or "", round(time.time() - t, 1), timed_out)
        self.log(result.output[-2_000_000:])
        self.log(f"-> exit {result.rc}{' (timed out)' if timed_out else ''} after {result.seconds} s\n")
        return result

    def stage(self, name: str, fn) -> None:
        entry: dict = {"status": "skipped", "seconds": 0.0}
        if name not in self.selected:
            entry["details"] = {"reason": "not selected (GPU_CHECK_STAGES)"}
        elif name in CUDA_ONLY and not self.cuda:
            entry["details"] = {"reason": "needs CUDA"}
        else:
            default = LIMITS[name]
            limit = float(os.environ.get(f"GPU_CHECK_TIMEOUT_{name.upper()}", default))
            limit = max(1.0, min(limit, self.remaining() - 5))
            self.log(f"==== stage {name} (limit {limit:.0f} s, {self.remaining():.0f} s left in the budget)")
            t = time.time()
            try:
                status, details = fn(limit)
            except Exception as e:  # a broken stage is recorded, the next one runs
                status, details = "failed", {"error": f"{type(e).__name__}: {e}",
                                             "traceback": traceback.format_exc()[-1500:]}
                self.log(traceback.format_exc())
            entry = {"status": status, "seconds": round(time.time() - t, 1), "limit_s": round(limit),
                     "details": details}
            self.log(f"==== stage {name}: {status} in {entry['seconds']} s")
        self.result["stages"][name] = entry
        self.save()

    # ------------------------------------------------------------------ stages
    def env_stage(self, limit: float):
        probe = self.run([self.py, "-c", env_probe_code()], limit)
        info: dict = {"python_executable": self.py, "cpus": os.cpu_count(), "forced_cpu": self.forced_cpu,
                      "source_sha256": source_digest()}
        try:  # the device tool's copy of a checkout may come without .git, the machine without git
            git = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True)
            info["git_commit"] = git.stdout.strip() if git.returncode == 0 else None
        except OSError:
            info["git_commit"] = None
        if shutil.which("nvidia-smi") and not self.forced_cpu:
            smi = self.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
                           20)
            info["nvidia_smi"] = smi.output.strip() if smi.rc == 0 else f"failed: {smi.output.strip()[-300:]}"
        if probe.rc != 0:
            info["probe_error"] = probe.output[-1500:]
            self.result["device"] = info
            return "failed", info
        info.update(json.loads(probe.output.strip().splitlines()[-1]))
        self.cuda = bool(info.get("cuda_available"))
        self.result["device"] = info
        self.result["cuda"] = self.cuda
        self.total = float(os.environ.get("GPU_CHECK_SECONDS", 450 if self.cuda else 900))
        self.result["budget_s"] = self.total
        return "ok", {k: info.get(k) for k in ("gpu_name", "torch", "torch_cuda", "cuda_available")}

    def bench_stage(self, limit: float):
        bench = str(ROOT / "benchmarks" / "bench_gpu.py")
        if not self.cuda:
            path = self.work / "bench_cpu.json"
            r = self.run([self.py, bench, "--device", "cpu", "--resolution", "32", "--json", str(path)], limit)
            details = {"cuda_figures": "skipped: no CUDA", "cpu_op_count": read_json(path), "rc": r.rc,
                       "timed_out": r.timed_out}
            return ("ok" if r.rc == 0 else "failed"), details
        details, ok = {}, True
        gather = str(ROOT / "benchmarks" / "bench_gather.py")
        variants = str(ROOT / "benchmarks" / "bench_view_variants.py")
        chosen = os.environ.get("GPU_CHECK_VIEW_VARIANTS", "").replace(",", " ").split()
        view_variants = ["--variants", *chosen] if chosen else []
        cases = [("baseline", [bench, "--depth", "none"], 0.3),
                 ("compiled", [bench, "--depth", "none", "--compile", "--repeat", "10"], 0.5),
                 ("compiled_step", [bench, "--depth", "none", "--compile-step", "--no-views", "--repeat", "10"], 0.75),
                 ("view_variants", [variants, "--budget-s", "{budget}", *view_variants], 0.7),
                 ("depth_aware", [bench, "--depth", "bundled", "--no-views"], 0.8), ("gather", [gather], 1.0)]
        try:
            cases = bench_cases(cases, os.environ.get("GPU_CHECK_BENCH_CASES", ""))
        except ValueError as e:
            return "failed", {"error": str(e)}
        t_end = time.time() + limit
        for name, args, share in cases:
            path = self.work / f"bench_{name}.json"
            left = t_end - time.time()
            # a case that takes a budget starts no new variant after 70% of its time limit (each compiles first)
            args = [a.replace("{budget}", f"{0.7 * left * share:.0f}") for a in args]
            r = self.run([self.py, *args, "--json", str(path)], left * share)
            details[name] = {**read_json(path), "rc": r.rc, "timed_out": r.timed_out}
            if r.rc != 0:
                details[name]["output_tail"] = r.output[-800:]
                ok = False
        return ("ok" if ok else "failed"), details

    def data_stage(self, limit: float):
        s = self.settings()
        cmd = [self.py, "-m", "depthnerf", "synth", "--category", "cars", "--out", str(self.work / "data"),
               "--train-objects", str(s["objects"]), "--val-objects", "0", "--test-objects", "0",
               "--resolution", str(s["res"]), "--views-train", str(s["views"]), "--seed", "0",
               "--workers", str(min(8, os.cpu_count() or 1)), "--quiet"]
        r = self.run(cmd, limit)
        return ("ok" if r.rc == 0 else "failed"), {"rc": r.rc, "timed_out": r.timed_out,
                                                   "output_tail": r.output[-400:]}

    def settings(self) -> dict:
        e, cuda = os.environ.get, self.cuda
        every = int(e("GPU_CHECK_CKPT_EVERY", 50 if cuda else 2))
        tiny = ("--data.num_workers 0 --model.encoder.backbone resnet18 --model.coarse.d_hidden 32 "
                "--model.fine.d_hidden 32 --render.sampler.n_coarse 8 --render.sampler.n_importance 4 "
                "--render.sampler.n_gaussian 4 --schedule.objects_phase1 2 --schedule.objects_phase2 2 "
                "--schedule.rays_per_object 32")
        return {"steps": int(e("GPU_CHECK_STEPS", 200 if cuda else 6)), "every": every,
                "crash": e("GPU_CHECK_CRASH", f"state@{2 * every}"), "res": int(e("GPU_CHECK_RES", 128 if cuda else 32)),
                "objects": int(e("GPU_CHECK_OBJECTS", 8 if cuda else 2)),
                "views": int(e("GPU_CHECK_VIEWS", 24 if cuda else 4)),
                "preset": e("GPU_CHECK_PRESET", "paper-cars"), "depth": e("GPU_CHECK_DEPTH", "oracle"),
                "train_args": shlex.split(e("GPU_CHECK_TRAIN_ARGS", "--data.num_workers 2" if cuda else tiny)),
                "device": "cuda" if cuda else "cpu"}

    def train_stage(self, limit: float):
        s = self.settings()
        self.result["train_settings"] = {k: v for k, v in s.items()}
        plan = train_plan(self.py, self.work, s, self.cuda)
        logs = self.work / "logs"
        logs.mkdir(exist_ok=True)
        procs: dict[str, subprocess.Popen] = {}
        handles = {}
        t_end, t0 = time.time() + limit, time.time()
        details: dict = {name: {} for name in plan}

        def start(name: str, cmd: list[str], env: dict) -> None:
            self.log(f"$ {' '.join(f'{k}={v}' for k, v in env.items())} {shlex.join(cmd)}  (log {logs / name}.log)")
            handles[name] = open(logs / f"{name}.log", "a")
            procs[name] = subprocess.Popen(cmd, cwd=ROOT, env={**self.env, **env}, stdout=handles[name],
                                           stderr=subprocess.STDOUT, start_new_session=True)

        for name, (cmd, env, _) in plan.items():
            start(name, cmd, env)
        timed_out = False
        while procs:
            for name, p in list(procs.items()):
                if p.poll() is None:
                    continue
                del procs[name]
                handles[name].close()
                key = "rc" if "rc" not in details[name] else "resume_rc"
                details[name][key] = p.returncode
                details[name][key.replace("rc", "seconds")] = round(time.time() - t0, 1)
                resume = plan[name][2]
                if resume is not None and key == "rc" and not timed_out:
                    metrics = self.work / "runs" / name / "metrics.jsonl"  # resume drops the lines after its step
                    if metrics.is_file():
                        shutil.copy(metrics, self.work / "runs" / f"{name}.killed.jsonl")
                    start(name, resume, {})
            if procs and not timed_out and time.time() > t_end:
                timed_out = True
                for name, p in procs.items():
                    stop_group(p, signal.SIGTERM)
                    details[name]["killed_at_limit"] = True
                continue
            time.sleep(0.2)
        ok = not timed_out
        for name in plan:
            text = (logs / f"{name}.log").read_text(errors="replace")
            self.log(f"---- {name}.log (last 4000 characters)\n{text[-4000:]}")
            d = details[name]
            if name == "b":
                stage, crash_step = s["crash"].split("@")[0], int(s["crash"].split("@")[1])
                d["crash_at"] = s["crash"]
                d["expected_resume_step"] = crash_step - s["every"] if stage in ("weights", "optimizer", "state") \
                    else crash_step
                said = [line for line in text.splitlines() if line.startswith("resumed from step")]
                d["resume_said"] = said[-1][:200] if said else None
                good = d.get("rc") == -signal.SIGKILL and d.get("resume_rc") == 0 and bool(said) and \
                    said[-1].startswith(f"resumed from step {d['expected_resume_step']} (")
            else:
                good = d.get("rc") == 0
            if not good:
                d["log_tail"] = text[-600:]
            ok &= good
        details["timed_out"] = timed_out
        return ("ok" if ok else "failed"), details

    def compare_stage(self, a: str, b: str, exact: bool):
        def fn(limit: float):
            ra, rb = self.work / "runs" / a, self.work / "runs" / b
            killed = self.work / "runs" / f"{b}.killed.jsonl"
            cmd = [self.py, str(ROOT / "scripts" / "gpu_check_parts.py"), "compare", str(ra), str(rb)]
            r = self.run(cmd + ([str(killed)] if killed.is_file() else []), limit)
            if r.rc != 0:
                return "failed", {"rc": r.rc, "timed_out": r.timed_out, "output_tail": r.output[-1200:]}
            details = json.loads(r.output.strip().splitlines()[-1])
            if not exact:
                return "ok", details
            return ("ok" if details["identical"] else "failed"), details
        return fn

    def pytest_stage(self, limit: float):
        plugin_dir = self.work / "pytest_plugin"
        plugin_dir.mkdir(exist_ok=True)
        shutil.copy(Path(__file__).with_name("gpu_check_pytest.py"), plugin_dir)
        report = self.out / "pytest_report.jsonl"
        report.unlink(missing_ok=True)
        have = json.loads(self.run([self.py, "-c", "import importlib.util as u, json; print(json.dumps("
                                    "[u.find_spec(m) is not None for m in ('xdist', 'pytest_timeout')]))"],
                                   30).output.strip().splitlines()[-1])
        cmd = [self.py, "-m", "pytest", "-p", "gpu_check_pytest", "-p", "no:cacheprovider", "-rfE"]
        cpus = os.cpu_count() or 1
        workers = int(os.environ.get("GPU_CHECK_PYTEST_WORKERS", min(8, cpus // 2) if have[0] and cpus >= 4 else 0))
        threads = max(1, cpus // max(1, workers)) if workers else int(os.environ.get("OMP_NUM_THREADS", 0) or cpus)
        if workers and have[0]:
            cmd += ["-n", str(workers)]
        if have[1]:
            cmd += ["--timeout", os.environ.get("GPU_CHECK_TEST_TIMEOUT", "120")]
        cmd += shlex.split(os.environ.get("GPU_CHECK_PYTEST_ARGS", ""))
        grace = min(60.0, 0.25 * limit)
        env = {"GPU_CHECK_DEADLINE": str(time.time() + limit - grace), "GPU_CHECK_REPORT": str(report),
               "GPU_CHECK_ACTIVE": "1", "OMP_NUM_THREADS": str(threads),
               "PYTHONPATH": f"{plugin_dir}:{self.env.get('PYTHONPATH', '')}"}
        r = self.run(cmd, limit, env=env, sig=signal.SIGINT)
        details = pytest_summary(report, r)
        details.update(workers=workers, threads_per_worker=threads, deadline_s=round(limit - grace),
                       args=cmd[3:])
        c = details["counts"]
        why = [f"{c[k]} {k}" for k in ("failed", "error") if c.get(k)]
        why += [f"{details[k]} {k.replace('_', ' ')}" for k in ("not_run_budget", "not_reached") if details[k]]
        why += [f"pytest exit {r.rc}"] if r.rc != 0 and not why else []
        why += ["stopped at the stage's limit"] if r.timed_out else []
        details["reason"] = "; ".join(why) or None
        return ("failed" if why else "ok"), details

    def main(self) -> int:
        self.stage("env", self.env_stage)
        if self.total is None:  # the probe failed: budget as on a GPU, the cautious choice
            self.total = float(os.environ.get("GPU_CHECK_SECONDS", 450))
        self.stage("bench", self.bench_stage)
        self.stage("data", self.data_stage)
        self.stage("train", self.train_stage)
        self.stage("resume_exact", self.compare_stage("a", "b", exact=True))
        self.stage("same_seed", self.compare_stage("a", "c", exact=True))
        self.stage("fast_kernels", self.compare_stage("f1", "f2", exact=False))
        self.stage("pytest", self.pytest_stage)
        self.result["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        self.save()
        print(headline(self.result))
        summary = " ".join(f"{k}={v}" for k, v in self.result["summary"].items())
        print(f"gpu_check: {summary} ({self.result['seconds']} s); {self.out / 'gpu_check.json'}")
        return 0 if all(v != "failed" for v in self.result["summary"].values()) else 1


def read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: gpu_check.py OUT_DIR  (normally through scripts/gpu_check.sh)")
    out_dir = Path(sys.argv[1])
    out_dir.mkdir(parents=True, exist_ok=True)
    sys.exit(Check(out_dir).main())
