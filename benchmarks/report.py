"""Cost of ``trackdeform report`` per recorded episode, and its extrapolation to a 1 h session (no assertions).

Usage: .venv/bin/python benchmarks/report.py [SESSION] [--seconds 20]
Without SESSION a simulated-time mock session of ``--seconds`` s is recorded first (tracking off); its runs
then have no keypoints, so the page is built twice: as recorded (reading /keypoints, journal, summary:
the streaming cost every report pays) and with ``--track-missing`` (offline tracking, every frame).
With the episodes' digests (``tdrecord.digest``, written by the recorder) the page is built as recorded
twice: reading the digests, and with them moved aside (every MCAP chunk decompressed). Printed: wall s,
s and CPU s per episode (the job processes' included), peak RSS of this process and of a job process (MB),
the CPU scaled to 720 episodes (1 h at 5 s episodes) and, for ``--jobs`` above 1, the 1 h wall estimated as
the job processes' start-up (this build's wall minus the 1-job wall shared out) plus the 1-job wall per
episode x 720 shared by the jobs (a short session is mostly start-up).
"""

from __future__ import annotations

import argparse
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from orchestrator.bus import free_port  # noqa: E402
from orchestrator.progress import Progress  # noqa: E402
from orchestrator.report import build_report, group_runs  # noqa: E402
from tdrecord.digest import DIGEST_SUFFIX  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session", nargs="?", help="a recorded session folder (default: record one)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the recorded session, s")
    ap.add_argument("--jobs", default="1,2", help="report processes to compare (build_report's jobs), comma-separated")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_report_"))
    session = Path(a.session) if a.session else tmp / "session"
    if not a.session:
        subprocess.run([sys.executable, "-m", "orchestrator.cli", "demo", "--sim-time", "--seconds", str(a.seconds),
                        "--out", str(session), "--port", str(free_port()), "--no-tracking"], check=True,
                       capture_output=True, cwd=Path(__file__).resolve().parent.parent)
    episodes = len(list(session.glob("episode_*.mcap")))
    runs = group_runs(sorted(session.glob("episode_*.mcap")))
    size = sum(p.stat().st_size for p in session.glob("episode_*.mcap"))
    print(f"session {session}: {episodes} episodes, {size / 1e9:.2f} GB")
    digests = sorted(session.glob(f"episode_*{DIGEST_SUFFIX}"))
    print(f"{len(digests)} episode digests ({sum(p.stat().st_size for p in digests) / 1e6:.1f} MB)")
    aside = tmp / "digests_aside"
    aside.mkdir()
    cases = []
    walls: dict[tuple[bool, bool, int], float] = {}
    for jobs in (int(j) for j in a.jobs.split(",")):
        cases += [(f"as recorded, digests, {jobs} job(s)", False, False, jobs)] if digests else []
        cases += [(f"as recorded, MCAP only, {jobs} job(s)", False, True, jobs)]
    cases += [("with --track-missing, 1 job", True, False, 1)]
    # warm-up (imports, matplotlib's font cache, page cache of the files): not counted
    build_report(session, tmp / "report_warmup", progress=Progress(enabled=False), jobs=1)
    for label, track, hide, jobs in cases:
        if hide:  # the episodes' small channels read from the MCAP files (every chunk decompressed)
            for p in digests:
                shutil.move(p, aside / p.name)  # another file system, e.g. a session on a tmpfs
        try:
            t0, c0 = time.monotonic(), time.process_time()
            k0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            build_report(session, tmp / f"report_{track}_{hide}_{jobs}", track_missing=track, jobs=jobs,
                         progress=Progress(enabled=False))
            k1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # the job processes, joined by build_report
            wall = time.monotonic() - t0
            cpu = time.process_time() - c0 + (k1.ru_utime + k1.ru_stime) - (k0.ru_utime + k0.ru_stime)
        finally:
            for p in digests:
                if (aside / p.name).exists():
                    shutil.move(aside / p.name, p)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        per = max(1, episodes)
        n = min(jobs, len(runs))
        walls[(track, hide, n)] = wall
        hour = f", 1 h (720 episodes) ~ {720 * cpu / per:.0f} s CPU"
        one = walls.get((track, hide, 1))
        if n > 1 and one is not None:  # start-up of the job processes (spawn, imports) + the work split n ways
            startup = max(0.0, wall - one / n)
            hour = (f", 1 h with {n} jobs ~ {startup + 720 * one / per / n:.0f} s wall (start-up {startup:.1f} s "
                     f"+ 720 x {one / per:.3f} s / {n}, the 1-job wall per episode shared by {n} cores)")
        elif n == 1:
            hour += f", ~ {720 * wall / per:.0f} s wall"
        print(f"{label:34s}: {wall:6.1f} s wall, {wall / per:5.2f} s/episode, {cpu / per:5.2f} s CPU/episode "
              f"(job processes included), peak RSS {rss:4.0f} MB (a job process {child:4.0f} MB)"
              + ("" if track else hour), flush=True)

if __name__ == "__main__":
    main()
