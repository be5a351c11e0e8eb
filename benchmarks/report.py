"""Cost of ``trackdeform report`` per recorded episode, and its extrapolation to a 1 h session (no assertions).

Usage: .venv/bin/python benchmarks/report.py [SESSION] [--seconds 20]
Without SESSION a simulated-time mock session of ``--seconds`` s is recorded first (tracking off); its runs
then have no keypoints, so the page is built twice: as recorded (reading /keypoints, journal, summary:
the streaming cost every report pays) and with ``--track-missing`` (offline tracking, every frame).
Printed: wall s, s per episode, peak RSS of this process (MB), and the first figure scaled to 720
episodes (1 h at 5 s episodes).
"""

from __future__ import annotations

import argparse
import resource
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from orchestrator.progress import Progress  # noqa: E402
from orchestrator.report import build_report  # noqa: E402


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("session", nargs="?", help="a recorded session folder (default: record one)")
    ap.add_argument("--seconds", type=float, default=20.0, help="length of the recorded session, s")
    a = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="bench_report_"))
    session = Path(a.session) if a.session else tmp / "session"
    if not a.session:
        subprocess.run([sys.executable, "-m", "orchestrator.cli", "demo", "--sim-time", "--seconds", str(a.seconds),
                        "--out", str(session), "--port", str(_port()), "--no-tracking"], check=True,
                       capture_output=True, cwd=Path(__file__).resolve().parent.parent)
    episodes = len(list(session.glob("episode_*.mcap")))
    size = sum(p.stat().st_size for p in session.glob("episode_*.mcap"))
    print(f"session {session}: {episodes} episodes, {size / 1e9:.2f} GB")
    for track in (False, True):
        t0 = time.monotonic()
        build_report(session, tmp / f"report_{track}", track_missing=track, progress=Progress(enabled=False))
        wall = time.monotonic() - t0
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        label = "with --track-missing" if track else "as recorded         "
        print(f"{label}: {wall:6.1f} s, {wall / max(1, episodes):5.2f} s/episode, peak RSS {rss:6.0f} MB"
              + ("" if track else f", 1 h (720 episodes) ~ {720 * wall / max(1, episodes):.0f} s"))


if __name__ == "__main__":
    main()
