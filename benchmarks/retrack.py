"""``trackdeform retrack`` throughput: frames per second with 1 and 2 local workers on one session (no assertions).

Usage: .venv/bin/python benchmarks/retrack.py [SESSION] [--seconds 120] [--workers 1,2] [--repeats 1] [--ray]
Without SESSION a simulated-time mock demo of ``--seconds`` s is recorded first (one 10 s program run per
pass: 120 s = 12 runs; the workers' start-up, ~2 s of imports each, is then a small part of the time, as in
a night's dataset, where it is negligible). Each configuration re-tracks the whole session into
a fresh keypoint version (deleted afterwards). Printed per configuration: frames, frames/s from the first
task submitted to the last result and over the whole call (process start-up included), the workers' CPU
s per frame and how many cores they got (CPU s / tracking s), the load average before and after; then
the speed-up of each worker count over the first. The target (issue 13) is 2 workers >= 1.8x the
frames/s of 1 on this 2-core machine: read the load average and the cores got beside it (a shared machine).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from orchestrator.bus import free_port  # noqa: E402
from orchestrator.config import DEFAULT_CONFIG, load_config  # noqa: E402
from orchestrator.progress import Progress  # noqa: E402
from orchestrator.retrack import VERSIONS_DIR, retrack, session_runs  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session", nargs="?", help="a recorded session folder (default: record one)")
    ap.add_argument("--seconds", type=float, default=120.0, help="length of the recorded session, s")
    ap.add_argument("--workers", default="1,2", help="worker counts to compare, comma-separated")
    ap.add_argument("--repeats", type=int, default=1, help="measurements per worker count (alternating)")
    ap.add_argument("--ray", action="store_true", help="also run each worker count on a local Ray cluster")
    a = ap.parse_args()
    repo = Path(__file__).resolve().parent.parent
    tmp = Path(tempfile.mkdtemp(prefix="bench_retrack_"))
    session = Path(a.session) if a.session else tmp / "session"
    if not a.session:
        subprocess.run([sys.executable, "-m", "orchestrator.cli", "demo", "--sim-time", "--seconds", str(a.seconds),
                        "--out", str(session), "--port", str(free_port()), "--no-tracking"], check=True,
                       capture_output=True, cwd=repo)
    config = load_config(DEFAULT_CONFIG)
    runs = session_runs(session, config.tracking)
    print(f"session {session}: {len(runs)} runs, {sum(len(r.episodes) for r in runs)} episodes, "
          f"{sum(r.frames for r in runs)} frames; {os.cpu_count()} cores")
    counts = [int(x) for x in a.workers.split(",")]
    backends = [None, "local"] if a.ray else [None]
    figures: dict[tuple[str, int], list[float]] = {}
    for rep in range(a.repeats):
        order = counts if rep % 2 == 0 else counts[::-1]
        for ray in backends:
            for n in order:
                name = f"bench-{os.getpid()}-{'ray' if ray else 'local'}-w{n}-{rep}"
                load0 = os.getloadavg()[0]
                t0 = time.monotonic()
                s = retrack(session, config, version=name, workers=n, ray_address=ray,
                            progress=Progress(enabled=False))
                wall = time.monotonic() - t0
                load1 = os.getloadavg()[0]
                shutil.rmtree(session / VERSIONS_DIR / name)
                fps = s.frames / s.tracking_s
                key = ("ray" if ray else "local", n)
                figures.setdefault(key, []).append(fps)
                print(f"{key[0]:5s} {n} worker(s): {s.frames} frames, {fps:6.2f} frames/s (tracking), "
                      f"{s.frames / wall:6.2f} frames/s (whole call, {wall:5.1f} s), "
                      f"{1e3 * s.cpu_s / max(1, s.frames):5.1f} ms CPU/frame, the workers got "
                      f"{s.cpu_s / s.tracking_s:4.2f} cores, load {load0:.1f} -> {load1:.1f}"
                      + (f", {len(s.failed)} run(s) failed" if s.failed else ""), flush=True)
    for backend in {k[0] for k in figures}:
        base = figures.get((backend, counts[0]))
        for n in counts[1:]:
            if base and (backend, n) in figures:
                best = max(figures[(backend, n)]) / max(base)
                mean = (sum(figures[(backend, n)]) / len(figures[(backend, n)])) / (sum(base) / len(base))
                print(f"{backend}: {n} workers / {counts[0]}: {mean:.2f}x (mean of {len(base)}), "
                      f"{best:.2f}x (best of each)")
    shutil.rmtree(tmp)


if __name__ == "__main__":
    main()
