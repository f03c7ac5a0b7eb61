"""Pieces of scripts/gpu_check.py: the training plan, the bit-for-bit run comparison, the pytest summary, the
environment probe. ``python scripts/gpu_check_parts.py compare RUN_A RUN_B [KILLED_METRICS]`` prints the
comparison of two run folders as one JSON line (every logged loss term of every step, the final checkpoint's
weights and optimiser state; with KILLED_METRICS, also the steps the killed process of RUN_B logged before its
kill, which ``--resume`` drops from ``metrics.jsonl`` and logs again). ``python scripts/gpu_check_parts.py digest``
prints :func:`source_digest` of this checkout, to match the ``source_sha256`` of a gpu_check.json to a commit."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
BUDGET_REASON = "gpu_check: time budget spent"  # the same text as gpu_check_pytest.BUDGET_REASON
RATE_KEYS = ("rays_per_s",)
"""Logged per-step values that measure speed, not the computation: left out of the comparison."""


@dataclass
class Proc:
    rc: int
    output: str
    seconds: float
    timed_out: bool


def signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


def stop_group(proc: subprocess.Popen, sig: int = signal.SIGTERM, grace: float = 15) -> None:
    """Send ``sig`` to the process group of ``proc`` (a training run checkpoints on SIGTERM), SIGKILL after
    ``grace`` seconds; returns once it has exited. For processes whose output goes to a file, not a pipe."""
    signal_group(proc, sig)
    try:
        proc.wait(grace)
    except subprocess.TimeoutExpired:
        signal_group(proc, signal.SIGKILL)
        proc.wait()


def source_digest() -> str:
    """sha256 of the checkout's Python, shell and pyproject files (which code ran, where there is no .git)."""
    h = hashlib.sha256()
    files = [ROOT / "pyproject.toml"]
    for folder in ("depthnerf", "scripts", "benchmarks", "tests"):
        files += [p for p in (ROOT / folder).rglob("*") if p.suffix in (".py", ".sh") and p.is_file()]
    for path in sorted(files):
        h.update(str(path.relative_to(ROOT)).encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def env_probe_code() -> str:
    """Python source that prints the device facts as one JSON line (run in a subprocess: CUDA starts there)."""
    return """
import importlib.util, json, platform, sys, torch
d = {"python": platform.python_version(), "torch": torch.__version__, "torch_cuda": torch.version.cuda,
     "cuda_available": torch.cuda.is_available(),
     "cudnn": torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
     "gpu_name": None}
if d["cuda_available"]:
    p = torch.cuda.get_device_properties(0)
    d.update(gpu_name=torch.cuda.get_device_name(0), gpu_count=torch.cuda.device_count(),
             gpu_capability=".".join(map(str, torch.cuda.get_device_capability(0))),
             gpu_memory_gib=round(p.total_memory / 2**30, 1), gpu_multiprocessors=p.multi_processor_count)
mods = ("trimesh", "embreex", "rtree", "lpips", "safetensors", "transformers", "skimage", "xdist", "pytest_timeout")
d["packages"] = {m: importlib.util.find_spec(m) is not None for m in mods}
print(json.dumps(d))
"""


def bench_cases(cases: list[tuple[str, list[str], float]], chosen: str) -> list[tuple[str, list[str], float]]:
    """The bench stage's cases that ``chosen`` names (``GPU_CHECK_BENCH_CASES``: names separated by spaces or
    commas; empty: all), in the stage's order, the last one given all the time left (share 1.0). An unknown name
    is a ValueError naming it."""
    names = chosen.replace(",", " ").split()
    if not names:
        return cases
    unknown = sorted(set(names) - {name for name, _, _ in cases})
    if unknown:
        raise ValueError(f"GPU_CHECK_BENCH_CASES: unknown cases {unknown}; known: {[c[0] for c in cases]}")
    picked = [case for case in cases if case[0] in names]
    return [*picked[:-1], (*picked[-1][:2], 1.0)]


def train_plan(py: str, work: Path, s: dict, cuda: bool) -> dict[str, tuple[list[str], dict, list[str] | None]]:
    """name -> (command, extra environment, command run after it exits or None): ``a`` uninterrupted, ``c`` the
    same again, ``b`` killed by the checkpoint writer's hook then resumed (all ``--deterministic``); on CUDA also
    ``f1`` / ``f2`` with the default (fast, non-deterministic) kernels."""
    base = [py, "-m", "depthnerf", "train", "--preset", s["preset"], "--data", str(work / "data"),
            "--depth", s["depth"], "--seed", "0", "--max-steps", str(s["steps"]),
            "--checkpoint-every", str(s["every"]), "--device", s["device"], "--log.val_every", "0",
            "--log.log_every", "1", "--no-progress", "--data.resolution", str(s["res"]), *s["train_args"]]
    det = [*base, "--deterministic"]
    runs = work / "runs"
    plan = {name: ([*det, "--out", str(runs / name)], {}, None) for name in ("a", "c")}
    plan["b"] = ([*det, "--out", str(runs / "b")], {"DEPTHNERF_CRASH_AT": s["crash"]},
                 [*det, "--out", str(runs / "b"), "--resume"])
    if cuda:
        plan.update({name: ([*base, "--out", str(runs / name)], {}, None) for name in ("f1", "f2")})
    return plan


def _metrics(path: Path) -> dict[int, dict]:
    """Logged values per step of a ``metrics.jsonl`` (the last line of a step, rates left out)."""
    out: dict[int, dict] = {}
    for line in path.read_text().splitlines():
        m = json.loads(line)
        if "loss" in m:
            out[m["step"]] = {k: v for k, v in m.items() if k not in RATE_KEYS}
    return out


def _tensors(a: dict, b: dict) -> dict:
    import torch

    differing, worst = [], 0.0
    for k in sorted(set(a) & set(b)):
        if a[k].shape != b[k].shape or not torch.equal(a[k], b[k]):
            differing.append(k)
            if a[k].shape == b[k].shape and a[k].is_floating_point():
                worst = max(worst, float((a[k].double() - b[k].double()).abs().max()))
    return {"tensors": len(set(a) | set(b)), "differing": len(differing) + len(set(a) ^ set(b)),
            "max_abs_diff": worst, "first_differing": differing[:5]}


def compare(a: Path, b: Path, killed: Path | None = None) -> dict:
    from safetensors.torch import load_file

    from depthnerf.train.checkpoint import latest_checkpoint

    la, lb = _metrics(a / "metrics.jsonl"), _metrics(b / "metrics.jsonl")
    steps = sorted(set(la) | set(lb))
    bad = [s for s in steps if la.get(s) != lb.get(s)]
    rel = [abs(la[s]["loss"] - lb[s]["loss"]) / max(abs(la[s]["loss"]), 1e-12) for s in steps if s in la and s in lb]
    out = {"steps_a": len(la), "steps_b": len(lb), "steps_differing": len(bad),
           "first_differing_step": bad[0] if bad else None, "max_rel_loss_diff": max(rel, default=None)}
    if killed is not None:  # what the killed process logged, against the uninterrupted run
        lk = _metrics(killed)
        out["killed_steps"] = len(lk)
        out["killed_steps_identical"] = all(la.get(s) == v for s, v in lk.items())
    ca, cb = latest_checkpoint(a / "checkpoints"), latest_checkpoint(b / "checkpoints")
    out["checkpoints"] = [ca.name if ca else None, cb.name if cb else None]
    identical = not bad and la.keys() == lb.keys() and ca is not None and cb is not None and ca.name == cb.name
    for name in ("model", "optimizer"):
        if ca is None or cb is None:
            continue
        out[name] = _tensors(load_file(ca / f"{name}.safetensors"), load_file(cb / f"{name}.safetensors"))
        identical &= out[name]["differing"] == 0
    out["identical"] = bool(identical and out.get("killed_steps_identical", True))
    return out


def pytest_summary(report: Path, proc: Proc) -> dict:
    """Counts, failing ids, skip reasons and the slowest tests from the plugin's JSON lines."""
    collected, ids, phases = 0, [], {}
    if report.is_file():
        for line in report.read_text().splitlines():
            r = json.loads(line)
            if "collected" in r:
                if r["collected"] >= collected:
                    collected, ids = r["collected"], r.get("ids", [])
            else:
                phases.setdefault(r["nodeid"], []).append(r)
    counts: Counter = Counter()
    failures, skips, durations, budget, unfinished = [], Counter(), [], 0, set()
    for nodeid, rs in phases.items():
        bad = [r for r in rs if r["outcome"] == "failed"]
        call = next((r for r in rs if r["when"] == "call"), None)
        skipped = next((r for r in rs if r["outcome"] == "skipped"), None)
        if call is not None:
            durations.append((call["duration"], nodeid))
        if bad:
            kind = "failed" if any(r["when"] == "call" for r in bad) else "error"
            counts[kind] += 1
            failures.append({"id": nodeid, "when": bad[0]["when"], "message": bad[0]["message"]})
        elif skipped is not None and skipped["xfail"]:
            counts["xfailed"] += 1
        elif skipped is not None:
            counts["skipped"] += 1
            if skipped["message"] == BUDGET_REASON:
                budget += 1
                unfinished.add(nodeid)
            skips[skipped["message"][:160]] += 1
        elif call is not None:
            counts["xpassed" if call["xfail"] else "passed"] += 1
    tail = [line for line in proc.output.splitlines() if line.strip()]
    words = ("passed", "failed", "skipped", "error", "no tests ran")
    summary = next((line for line in reversed(tail) if " in " in line and any(w in line for w in words)), None)
    unfinished |= {i for i in ids if i not in phases}
    return {"returncode": proc.rc, "timed_out": proc.timed_out, "collected": collected, "counts": dict(counts),
            "not_run_budget": budget, "not_reached": max(0, collected - len(phases)),
            "rerun_files": sorted({i.split("::")[0] for i in unfinished}),
            "failures": failures[:40], "failures_listed": min(40, len(failures)),
            "skip_reasons": dict(skips.most_common(12)),
            "slowest": [[round(d, 1), n] for d, n in sorted(durations, reverse=True)[:10]],
            "summary_line": summary}


if __name__ == "__main__":
    if sys.argv[1:] == ["digest"]:
        print(source_digest())
    elif len(sys.argv) in (4, 5) and sys.argv[1] == "compare":
        print(json.dumps(compare(*map(Path, sys.argv[2:]))))
    else:
        raise SystemExit("usage: gpu_check_parts.py compare RUN_A RUN_B [KILLED_METRICS] | digest")


def headline(result: dict) -> str:
    """The figures a person looks for first, a few lines (the device tool shows the end of the output)."""
    st = result["stages"]
    dev = result.get("device", {})
    lines = [f"device: {dev.get('gpu_name') or 'no GPU'} ({dev.get('nvidia_smi', '-')}), torch {dev.get('torch')}, "
             f"CUDA {dev.get('torch_cuda')}"]
    for name, entry in st.items():
        d = entry.get("details", {})
        if name == "bench" and "baseline" in d:
            b, a = d["baseline"], d.get("depth_aware", {})
            keys = ("train_ms_best", "kernel_launches_per_step", "peak_memory_gib", "view_paper_ms", "view_guided_ms",
                    "eval_704x250_paper_gpu_hours", "eval_704x250_guided_gpu_hours")
            lines.append("bench baseline: " + ", ".join(f"{k} {b.get(k)}" for k in keys))
            if "gather" in d:
                lines.append("bench gather ms: " + ", ".join(f"{k} {v.get('ms')}" for k, v in d["gather"].items()
                                                             if isinstance(v, dict)))
            if "compiled" in d:
                lines.append("bench --compile: " + ", ".join(f"{k} {d['compiled'].get(k)}"
                                                            for k in ("compile_warmup_s", *keys)))
            if "compiled_step" in d:
                lines.append("bench --compile-step: " + ", ".join(
                    f"{k} {d['compiled_step'].get(k)}" for k in ("compile_warmup_s", "train_ms_best",
                                                                "kernel_launches_per_step", "host_launch_calls_per_step",
                                                                "peak_memory_gib")))
            for variant, row in d.get("view_variants", {}).get("variants", {}).items():
                lines.append(f"bench view {variant}: " + (row.get("skipped") or ", ".join(
                    f"{k} {row.get(k)}" for k in ("ms_per_view", "warmup_s", "psnr_vs_fp32"))))
            lines.append(f"bench depth-aware: train_ms_best {a.get('train_ms_best')}, "
                         f"kernel_launches_per_step {a.get('kernel_launches_per_step')}")
        elif name in ("resume_exact", "same_seed", "fast_kernels") and "identical" in d:
            lines.append(f"{name}: identical {d['identical']}, steps differing {d['steps_differing']}, "
                         f"max rel loss diff {d['max_rel_loss_diff']}")
        elif name == "pytest" and "counts" in d:
            lines.append(f"pytest: {d['counts']}, not run (budget) {d['not_run_budget']}, not reached "
                         f"{d['not_reached']}; rerun {len(d['rerun_files'])} files: {' '.join(d['rerun_files'][:8]) or '-'}"
                         f"{' ...' if len(d['rerun_files']) > 8 else ''}")
            lines += [f"  FAILED {f['id']}" for f in d["failures"][:15]]
    return "\n".join(lines)
