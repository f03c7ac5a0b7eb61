"""Seconds of one photo's reconstruction through the Python API and through ``depthnerf reconstruct``.

    python benchmarks/bench_api_vs_cli.py [--checkpoint cpu-cars-depth] [--views 8] [--mesh-resolution 64]
                                          [--threads N] [--busy K] [--repeats 1]

Each case runs in a fresh Python process on the same photo (default: the app's bundled car example) with the
same settings, and prints the whole process's wall seconds and the seconds of the reconstruction itself
(``Reconstructor.reconstruct``: preparing, encoding, rendering, meshing; from ``manifest.json``'s timings for
the CLI). Cases:

- ``api``: ``from depthnerf import Reconstructor``; ``Reconstructor.from_pretrained(...).reconstruct(photo)`` and
  ``save``; the package sets its process defaults on import (``depthnerf.cpu_runtime``).
- ``api-unconfigured``: the same with ``DEPTHNERF_PROCESS_DEFAULTS=0`` (the process keeps OpenMP's and glibc's
  defaults, as the API did before it configured itself).
- ``cli``: ``python -m depthnerf reconstruct PHOTO --checkpoint ... --out ...``.

``OMP_WAIT_POLICY`` is removed from the cases' environment (the point is what each entry point sets) and
``OMP_NUM_THREADS`` is ``--threads`` (default: unset, i.e. torch's default of one thread per core: the setting
the wait policy matters for). ``--busy K`` starts K busy-loop processes for the duration (a machine whose cores
are taken by other work; default 0). Also printed: CPU count and the 1-minute load average before and after,
since other work on the machine changes every figure. Asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

API_SCRIPT = """
import json, sys, time
from depthnerf import ReconstructConfig, Reconstructor
checkpoint, photo, out, views, mesh = sys.argv[1:6]
rec = Reconstructor.from_pretrained(checkpoint)
t = time.perf_counter()
result = rec.reconstruct(photo, config=ReconstructConfig(views=int(views), mesh_resolution=int(mesh)))
seconds = time.perf_counter() - t
rec.save(result, out)
print(json.dumps({"reconstruct_s": seconds}))
"""


def spin() -> None:
    """A busy loop (one core's worth of other work)."""
    while True:
        pass


def run_case(name: str, args: argparse.Namespace, out: Path) -> tuple[float, float]:
    """(process wall seconds, reconstruction seconds) of one case in a fresh process."""
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "DEPTHNERF_PROCESS_DEFAULTS")}
    env.pop("OMP_NUM_THREADS", None)
    if args.threads:
        env["OMP_NUM_THREADS"] = str(args.threads)
    if name == "api-unconfigured":
        env["DEPTHNERF_PROCESS_DEFAULTS"] = "0"
    settings = [str(args.views), str(args.mesh_resolution)]
    if name == "cli":
        cmd = [sys.executable, "-m", "depthnerf", "reconstruct", str(args.photo), "--checkpoint", args.checkpoint,
               "--out", str(out), "--views", settings[0], "--mesh-resolution", settings[1], "--no-progress"]
    else:
        cmd = [sys.executable, "-c", API_SCRIPT, args.checkpoint, str(args.photo), str(out), *settings]
    t = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise SystemExit(f"{name} failed ({proc.returncode}): {proc.stderr.strip()[-2000:]}")
    if name == "cli":
        timings = json.loads((out / "manifest.json").read_text())["timings"]
        seconds = sum(timings[k] for k in ("prepare_s", "encode_s", "render_s", "mesh_s"))
    else:
        seconds = json.loads(proc.stdout.strip().splitlines()[-1])["reconstruct_s"]
    return wall, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photo", type=Path, default=ROOT / "depthnerf" / "app" / "examples" / "car_rgba.png")
    parser.add_argument("--checkpoint", default="cpu-cars-depth", help="shipped name or path (default cpu-cars-depth)")
    parser.add_argument("--views", type=int, default=8, help="orbit views (default 8)")
    parser.add_argument("--mesh-resolution", type=int, default=64, help="marching-cubes samples (default 64)")
    parser.add_argument("--threads", type=int, help="OMP_NUM_THREADS of the cases (default: unset)")
    parser.add_argument("--busy", type=int, default=0, help="busy-loop processes running meanwhile (default 0)")
    parser.add_argument("--repeats", type=int, default=1, help="runs per case (default 1)")
    parser.add_argument("--cases", nargs="+", default=["cli", "api", "api-unconfigured"],
                        choices=["cli", "api", "api-unconfigured"])
    args = parser.parse_args()
    print(f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; {args.checkpoint}, {args.photo.name}, "
          f"{args.views} views, mesh {args.mesh_resolution}, OMP_NUM_THREADS {args.threads or 'unset'}, "
          f"{args.busy} busy-loop processes", flush=True)
    spinners = [mp.get_context("spawn").Process(target=spin, daemon=True) for _ in range(args.busy)]
    for p in spinners:
        p.start()
    try:
        with tempfile.TemporaryDirectory(prefix="bench_api_cli_") as tmp:
            for k in range(args.repeats):
                for name in args.cases:
                    wall, seconds = run_case(name, args, Path(tmp) / f"{name}-{k}")
                    print(f"{name:17s} process {wall:7.1f} s, reconstruct {seconds:7.1f} s", flush=True)
    finally:
        for p in spinners:
            p.terminate()
            p.join()
    print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
