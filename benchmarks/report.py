"""Cost of ``trackdeform report`` per recorded episode, and its extrapolation to a 1 h session (no assertions).

Usage: .venv/bin/python benchmarks/report.py [SESSION] [--seconds 20]
Without SESSION a simulated-time mock session of ``--seconds`` s is recorded first (tracking off); its runs
then have no keypoints, so the page is built twice: as recorded (reading /keypoints, journal, summary:
the streaming cost every report pays) and with ``--track-missing`` (offline tracking, every frame).
With the episodes' digests (``tdrecord.digest``, written by the recorder) the page is built as recorded
twice: reading the digests, and with them moved aside (every MCAP chunk decompressed). Printed: wall s,
s and CPU s per episode, peak RSS of this process (MB), and the CPU scaled to 720 episodes (1 h at 5 s
episodes).
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from orchestrator.bus import free_port  # noqa: E402
from orchestrator.progress import Progress  # noqa: E402
from orchestrator.report import build_report  # noqa: E402
from tdrecord.digest import DIGEST_SUFFIX  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session", nargs="?", help="a recorded session folder (default: record one)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the recorded session, s")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_report_"))
    session = Path(a.session) if a.session else tmp / "session"
    if not a.session:
        subprocess.run([sys.executable, "-m", "orchestrator.cli", "demo", "--sim-time", "--seconds", str(a.seconds),
                        "--out", str(session), "--port", str(free_port()), "--no-tracking"], check=True,
                       capture_output=True, cwd=Path(__file__).resolve().parent.parent)
    episodes = len(list(session.glob("episode_*.mcap")))
    size = sum(p.stat().st_size for p in session.glob("episode_*.mcap"))
    print(f"session {session}: {episodes} episodes, {size / 1e9:.2f} GB")
    digests = sorted(session.glob(f"episode_*{DIGEST_SUFFIX}"))
    print(f"{len(digests)} episode digests ({sum(p.stat().st_size for p in digests) / 1e6:.1f} MB)")
    aside = tmp / "digests_aside"
    aside.mkdir()
    cases = [("as recorded, digests", False, False)] if digests else []
    cases += [("as recorded, MCAP only", False, True), ("with --track-missing", True, False)]
    # warm-up (imports, matplotlib's font cache, page cache of the files): not counted
    build_report(session, tmp / "report_warmup", progress=Progress(enabled=False))
    for label, track, hide in cases:
        if hide:  # the episodes' small channels read from the MCAP files (every chunk decompressed)
            for p in digests:
                p.rename(aside / p.name)
        try:
            t0, c0 = time.monotonic(), time.process_time()
            build_report(session, tmp / f"report_{track}_{hide}", track_missing=track,
                         progress=Progress(enabled=False))
            wall, cpu = time.monotonic() - t0, time.process_time() - c0
        finally:
            for p in digests:
                if (aside / p.name).exists():
                    (aside / p.name).rename(p)
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        per = max(1, episodes)
        print(f"{label:23s}: {wall:6.1f} s wall, {wall / per:5.2f} s/episode, {cpu / per:5.2f} s CPU/episode, "
              f"peak RSS {rss:6.0f} MB" + ("" if track else f", 1 h (720 episodes) ~ {720 * cpu / per:.0f} s CPU"))


if __name__ == "__main__":
    main()
