"""Seconds from an upload to the page's novel views in ``depthnerf app``, through its HTTP API, on this machine.

    python benchmarks/bench_app.py [--views 8] [--mesh-resolution 64] [--repeats 2] [--plain]

Starts ``depthnerf app`` (a subprocess on a free localhost port, the shipped checkpoints, the app's defaults: 8
orbit views, a 64-sample mesh, depth-guided rendering unless --plain), waits until it serves (printed: start-up
seconds, which include loading the first checkpoint), then for each bundled example uploads it with
``gradio_client`` and calls the page's ``/reconstruct`` endpoint, i.e. exactly what the Reconstruct button does.
Printed per call: wall seconds from the start of the upload to the response (which carries the orbit video, GIF,
mesh and downloads: the novel views are complete by then, so this bounds "upload -> first novel views" from above),
the server's own "done in" seconds, and its per-stage timings. The first call per checkpoint also loads it (the
car's was preloaded at start-up); the best of ``--repeats`` is the steady state. Also printed: CPU count, torch
threads (``OMP_NUM_THREADS`` is passed through) and the 1-minute load average before and after, since other work on
the machine slows it.
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until_serving(url: str, proc: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise SystemExit(f"the app exited with status {proc.returncode}")
        try:
            with urllib.request.urlopen(url, timeout=5) as resp:
                if resp.status == 200:
                    return
        except OSError:
            time.sleep(0.5)
    raise SystemExit(f"the app did not serve {url} within {timeout} s")


def reconstruct_arguments(image, checkpoint: str, fill: float, views: int, guided: bool = True) -> dict:
    """Keyword arguments of the page's ``/reconstruct`` endpoint for one photo: the model menu's checkpoint, the
    fill it was trained at, ``views`` orbit views, depth-guided rendering or not, the empty text fields (which
    have no default in the API) and every other field at the page's default. Named, so a field added to the page cannot shift them;
    ``tests/test_app.py`` checks them against the page's API."""
    return {"image": image, "model": checkpoint, "ckpt_path": "", "prior_ckpt": "", "bg_model": "", "ratio": fill,
            "views": views, "guided": guided}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=8, help="orbit views per request (app default 8)")
    parser.add_argument("--mesh-resolution", type=int, default=64, help="app --mesh-resolution (default 64)")
    parser.add_argument("--repeats", type=int, default=2, help="calls per example (default 2)")
    parser.add_argument("--plain", action="store_true",
                        help="untick the page's depth-guided rendering (the checkpoint's own sampler)")
    args = parser.parse_args()
    from gradio_client import Client, handle_file

    from depthnerf import Reconstructor
    from depthnerf.app.logic import examples
    from depthnerf.pretrained.recommended import RECOMMENDED

    print(f"cpus {os.cpu_count()}, OMP_NUM_THREADS {os.environ.get('OMP_NUM_THREADS', 'unset')}, "
          f"load average (1 min) {os.getloadavg()[0]:.2f}")
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    with tempfile.TemporaryDirectory() as tmp:
        env = {**os.environ, "GRADIO_ANALYTICS_ENABLED": "False", "GRADIO_TEMP_DIR": str(Path(tmp) / "gradio"),
               "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "depthnerf", "app", "--port", str(port), "--views",
                                 str(args.views), "--mesh-resolution", str(args.mesh_resolution), "--work-dir",
                                 str(Path(tmp) / "runs")], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                env=env)
        try:
            wait_until_serving(url, proc, 300)
            print(f"app serving after {time.perf_counter() - t0:.1f} s (imports, first checkpoint loaded)")
            client = Client(url, verbose=False)
            for example in examples():
                checkpoint = RECOMMENDED["cars" if example.name.startswith("car") else "chairs"]
                fill = Reconstructor.from_pretrained(checkpoint).default_fill
                for k in range(args.repeats):
                    t = time.perf_counter()
                    out = client.predict(**reconstruct_arguments(handle_file(str(example)), checkpoint, fill,
                                                                 args.views, not args.plain),
                                         api_name="/reconstruct")
                    wall = time.perf_counter() - t
                    status, details = out[0], out[7]
                    done = re.search(r"done in ([0-9.]+) s", status)
                    stages = re.search(r"\*\*Timings\*\* (.*)", details or "")
                    print(f"{example.name} call {k + 1}: upload -> views, video, mesh {wall:.1f} s "
                          f"(server {done.group(1) if done else '?'} s; {stages.group(1) if stages else status})")
        finally:
            proc.terminate()
            proc.wait(timeout=30)
    print(f"load average (1 min) after {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
