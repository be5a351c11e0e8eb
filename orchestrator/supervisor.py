"""The session's tracking worker, supervised: restarted with backoff when it dies, hangs or stops tracking.

The worker declares the liveliness token ``<prefix>/<station>/worker/alive/<host>-<pid>`` once it is
ready; the supervisor watches that token, the child process and the keypoints the session accepts.
It restarts the worker when the process exits, when it is not ready within ``tracking.worker_start_timeout``,
when its token disappears while the process lingers, or when frames are being recorded but no keypoints
were accepted for ``tracking.worker_max_lag`` s. Each restart is reported as an incident.
"""

from __future__ import annotations

import logging
import os
import re
import signal
import socket
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from orchestrator.bus import Bus
from orchestrator.config import Config
from orchestrator.live import KeypointGate
from orchestrator.workerproc import WorkerProcess, start_worker

log = logging.getLogger(__name__)
TOKEN_GRACE_S = 5.0  # a live process whose token vanished this long ago is hung (or cut off the bus)


def describe_exit(rc: int) -> str:
    """``exit code 3`` or ``signal SIGKILL``."""
    if rc < 0:
        try:
            return f"signal {signal.Signals(-rc).name}"
        except ValueError:
            return f"signal {-rc}"
    return f"exit code {rc}"


class WorkerSupervisor:
    """Starts the worker, checks it every ``poll`` s on its own thread, restarts it with exponential backoff.

    ``report(kind, message)`` receives every incident (the session's health and events log).
    """

    def __init__(self, config: Config, out_dir: Path, bus: Bus, session_id: str, gate: KeypointGate,
                 report: Callable[[str, str], None], poll: float = 0.2) -> None:
        self.config = config
        self.out_dir = out_dir
        self.bus = bus
        self.session_id = session_id
        self.gate = gate
        self.report = report
        self.poll = poll
        self.restarts = 0
        self.given_up: str | None = None
        self.proc: WorkerProcess | None = None
        self._launched = 0.0
        self._alive_since: float | None = None
        self._token_lost: float | None = None
        self._failures = 0  # consecutive: reset once a worker has run for a while
        self._tokens: set[str] = set()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="worker-supervisor", daemon=True)
        host = re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())
        self._host = host
        self._token_prefix = bus.key("worker", "alive")
        bus.watch_liveliness(self._token_prefix + "/**", self._on_token)

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Launch the worker and start watching it."""
        self._launch()
        self._thread.start()

    def stop(self) -> None:
        """Stop watching, then stop the worker (SIGTERM, SIGKILL after 10 s)."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5.0)
        if self.proc is not None:
            self.proc.stop()

    def wait_ready(self, timeout: float, stop: threading.Event) -> bool:
        """Wait up to ``timeout`` s (or until ``stop``) for the worker's liveliness token; True when it is up."""
        deadline = time.monotonic() + timeout
        while not self._alive():
            if stop.is_set() or time.monotonic() > deadline or self.given_up:
                return False
            stop.wait(0.1)
        return True

    def status(self) -> dict[str, Any]:
        """Worker facts for the health message."""
        now = time.monotonic()
        alive = self._alive()
        lag = self.gate.lag_s()
        state = ("given_up" if self.given_up else "alive" if alive else
                 "starting" if self._alive_since is None else "unresponsive")
        return {
            "state": state, "alive": alive, "pid": self.proc.proc.pid if self.proc else None,
            "restarts": self.restarts, "lag_s": None if lag is None else round(lag, 3),
            "up_s": round(now - self._alive_since, 1) if self._alive_since is not None and alive else None,
            "given_up": self.given_up,
        }

    # ------------------------------------------------------------ internals
    def _launch(self) -> None:
        args = ["--session-id", self.session_id, "--parent-pid", str(os.getpid())]
        self.proc = start_worker(self.config, self.out_dir, args)
        self._launched = time.monotonic()
        self._alive_since = None
        self._token_lost = None
        log.info("tracking worker started (pid %d)", self.proc.proc.pid)

    def _on_token(self, sample: Any) -> None:
        key = str(sample.key_expr)
        with self._lock:
            if str(sample.kind).endswith("PUT"):
                self._tokens.add(key)
            else:
                self._tokens.discard(key)

    def _alive(self) -> bool:
        if self.proc is None:
            return False
        with self._lock:
            return f"{self._token_prefix}/{self._host}-{self.proc.proc.pid}" in self._tokens

    def _problem(self) -> str | None:
        """Why the current worker must be restarted, or None."""
        assert self.proc is not None
        t = self.config.tracking
        now = time.monotonic()
        pid = self.proc.proc.pid
        rc = self.proc.proc.poll()
        if rc is not None:
            return f"tracking worker (pid {pid}) exited with {describe_exit(rc)}"
        if self._alive():
            if self._alive_since is None:
                self._alive_since = now
                log.info("tracking worker (pid %d) ready after %.1f s", pid, now - self._launched)
            self._token_lost = None
            if now - self._alive_since > 60.0:
                self._failures = 0
            idle = self.gate.seconds_without_keypoints(self._alive_since)
            if idle is not None and idle > t.worker_max_lag:
                return f"tracking worker (pid {pid}) published no usable keypoints for {idle:.0f} s of recording"
            return None
        if self._alive_since is None:
            if now - self._launched > t.worker_start_timeout:
                return f"tracking worker (pid {pid}) not ready after {t.worker_start_timeout:.0f} s"
            return None
        self._token_lost = self._token_lost or now
        if now - self._token_lost > TOKEN_GRACE_S:
            return f"tracking worker (pid {pid}) lost its liveliness token {now - self._token_lost:.0f} s ago"
        return None

    def _loop(self) -> None:
        while not self._stop.wait(self.poll):
            if self.given_up:
                continue
            try:
                problem = self._problem()
            except Exception as e:  # the supervisor must outlive anything odd
                log.exception("worker supervision failed")
                problem = f"worker supervision: {type(e).__name__}: {e}"
            if problem is None:
                continue
            assert self.proc is not None
            self.proc.stop(timeout=2.0)
            t = self.config.tracking
            if self.restarts >= t.worker_max_restarts:
                self.given_up = f"{problem}; gave up after {self.restarts} restarts"
                self.report("worker_given_up", self.given_up)
                continue
            delay = min(t.worker_restart_backoff * 2.0 ** self._failures, t.worker_restart_backoff_max)
            self._failures += 1
            self.report("worker_restart", f"{problem}; restarting it in {delay:.1f} s "
                        f"(restart {self.restarts + 1}, log {self.proc.log_path})")
            if self._stop.wait(delay):
                return
            self.restarts += 1
            self._launch()
