"""Start and stop the tracking worker as a child process next to a session."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

from orchestrator.bus import local_endpoints
from orchestrator.config import Config
from orchestrator.procutil import popen_nice

log = logging.getLogger(__name__)


class WorkerProcess:
    """A ``trackdeform worker`` child that connects to this session's zenoh endpoints."""

    def __init__(self, proc: subprocess.Popen, log_path: Path) -> None:
        self.proc = proc
        self.log_path = log_path

    def stop(self, timeout: float = 10.0) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout`` s; returns the exit code."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                log.warning("tracking worker did not stop in %.0f s; killing it", timeout)
                self.proc.kill()
                self.proc.wait()
        return self.proc.returncode


def start_worker(config: Config, out_dir: Path, extra_args: list[str] | None = None) -> WorkerProcess:
    """Launch the worker with the session's config (as JSON), connected to its listen endpoints.

    ``extra_args`` go to ``orchestrator.worker`` (the supervisor passes ``--session-id`` and ``--parent-pid``).
    The worker runs at a lower CPU priority (nice 10): it takes the newest frame whenever it is
    free, so it adapts its rate, while the capture loop and the recorder must keep 30 Hz.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg_path = out_dir / "worker_config.json"
    cfg_path.write_text(json.dumps(config.model_dump(mode="json"), indent=2))
    log_path = out_dir / "worker.log"
    cmd = [sys.executable, "-m", "orchestrator.worker", str(cfg_path)]
    for e in local_endpoints(config.bus.listen) or config.bus.connect:
        cmd += ["--connect", e]
    cmd += extra_args or []
    with open(log_path, "ab") as logf:
        proc = popen_nice(
            cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            start_new_session=True,  # a terminal's Ctrl-C reaches the session only, which stops the worker itself
        )
    return WorkerProcess(proc, log_path)
