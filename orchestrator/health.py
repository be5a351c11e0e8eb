"""The session's state, health and control: ``health`` once a second, ``ctl/*`` queryables, ``events.jsonl``.

Keys under ``<prefix>/<station>/``:

- ``health`` (published every ``bus.health_period`` s, and answered to a get): JSON
  ``trackdeform.Health/1`` with the state, the current run and episode, progress and ETA, the
  measured camera and joint-state rates, the worker's liveliness and lag, free disk and time to
  full, and the last incidents.
- ``ctl/pause`` | ``ctl/resume`` | ``ctl/stop`` | ``ctl/skip`` (queryables): the reply is JSON
  ``{"ok": bool, "command", "state", "message"}``. Pause takes effect at the end of the current
  episode and holds the arms at rest; skip ends the current run (journaled ``skipped``).
- ``session/run`` (published on each run and every health period, answered to a get): the run
  being recorded (``tdcommon.wire.run_announcement``); the tracker follows it.
- ``schema/keypoints`` (answered to a get): the keypoint message's JSON Schema.

State transitions, control commands and incidents are appended to ``events.jsonl`` in the output folder.
"""

from __future__ import annotations

import json
import logging
import shutil
import threading
import time
from collections import deque
from collections.abc import Callable
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from orchestrator.bus import Bus
from orchestrator.summary import SessionSummary
from tdcommon.wire import KEYPOINTS_JSON_SCHEMA, encode_json, run_announcement

log = logging.getLogger(__name__)
STATES = ("idle", "initialising", "running", "paused", "recovering", "stopping", "done", "failed")
COMMANDS = ("pause", "resume", "stop", "skip")
HEALTH_SCHEMA = "trackdeform.Health/1"


class EventLog:
    """Append-only JSON lines (``events.jsonl``): one ``write`` per event, flushed at once."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._f = open(path, "a", encoding="utf-8")
        self._lock = threading.Lock()

    def write(self, event: str, **fields: Any) -> dict[str, Any]:
        """Append ``{"time": UTC ISO, "stamp": unix s, "event": event, **fields}``; returns the record."""
        rec = {"time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"), "stamp": round(time.time(), 3),
               "event": event, **fields}
        with self._lock:
            if not self._f.closed:
                self._f.write(json.dumps(rec) + "\n")
                self._f.flush()
        return rec

    def close(self) -> None:
        """Close the file (later writes are dropped)."""
        with self._lock:
            self._f.close()


class _Rate:
    """Events per second of a growing counter over the last ``window`` s."""

    def __init__(self, window: float = 5.0) -> None:
        self.window = window
        self._samples: deque[tuple[float, float]] = deque()

    def update(self, t: float, value: float) -> float | None:
        """Add ``value`` at time ``t``; the rate (per s) over the window, None before two samples."""
        self._samples.append((t, value))
        while len(self._samples) > 2 and t - self._samples[0][0] > self.window:
            self._samples.popleft()
        t0, v0 = self._samples[0]
        return (value - v0) / (t - t0) if t > t0 else None


class SessionMonitor:
    """State, incidents and control of one session; publishes health and answers ``ctl`` on ``bus`` (optional).

    ``progress()`` returns the session's plan progress (runs_done, runs_planned, plan_pass); ``worker()``
    the worker's facts or None; ``stop_event`` is the session's stop (``ctl stop`` sets it).
    """

    def __init__(self, out_dir: Path, summary: SessionSummary, stop_event: threading.Event, *,
                 bus: Bus | None = None, session_id: str = "", period: float = 1.0, min_free_gb: float = 0.0,
                 progress: Callable[[], dict[str, Any]] | None = None,
                 worker: Callable[[], dict[str, Any] | None] | None = None,
                 keypoints: Callable[[], dict[str, Any]] | None = None) -> None:
        self.out_dir = out_dir
        self.summary = summary
        self.stop_event = stop_event
        self.bus = bus
        self.session_id = session_id
        self.period = period
        self.min_free_gb = min_free_gb
        self._progress = progress or (lambda: {})
        self._worker = worker or (lambda: None)
        self._keypoints = keypoints or (lambda: {})
        self.events = EventLog(out_dir / "events.jsonl")
        self.state = "idle"
        self.incidents: deque[dict[str, Any]] = deque(maxlen=10)
        self.run: dict[str, Any] = {}  # label, run_id, object, ... of the run being recorded
        self.position: dict[str, Any] = {}  # episode, frame in the run, frames in the run
        self.max_seconds: float | None = None
        self._announcement: dict[str, Any] = run_announcement(session_id=session_id, run_id="", run={}, stamp=0.0)
        self._pause = threading.Event()
        self._skip = threading.Event()
        self._resume = threading.Event()
        self._lock = threading.Lock()
        self._t0 = time.monotonic()
        self._cam_rate, self._state_rate, self._disk_rate = _Rate(), _Rate(), _Rate(30.0)
        self._last_health: dict[str, Any] = {}
        self._thread: threading.Thread | None = None
        self._stop_thread = threading.Event()
        self.events.write("session", session_id=session_id, out_dir=str(out_dir))
        if bus is not None:
            bus.queryable(bus.key("health"), lambda q: q.reply(q.key_expr, encode_json(self.health())))
            bus.queryable(bus.key("session", "run"), lambda q: q.reply(q.key_expr, encode_json(self._announcement)))
            bus.queryable(bus.key("schema", "keypoints"), lambda q: q.reply(q.key_expr, encode_json(
                KEYPOINTS_JSON_SCHEMA)))
            bus.queryable(bus.key("ctl", "*"), self._on_ctl)

    # ------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Publish health every ``period`` s on a thread (with a bus)."""
        if self.bus is not None and self._thread is None:
            self._thread = threading.Thread(target=self._publish_loop, name="health", daemon=True)
            self._thread.start()

    def close(self, final_state: str) -> None:
        """Enter ``final_state`` (done / failed), publish it once more and stop."""
        self.set_state(final_state)
        self._stop_thread.set()
        if self._thread is not None:
            self._thread.join(5.0)
        if self.bus is not None:
            try:
                self.bus.put(self.bus.key("health"), encode_json(self.health()))
            except Exception as e:  # the bus may be closing
                log.debug("last health message not sent: %s", e)
        self.events.close()

    # ------------------------------------------------------------ what the session tells
    def set_state(self, state: str, reason: str = "") -> None:
        """Enter ``state`` (one of STATES); a change is logged to events.jsonl."""
        if state not in STATES:
            raise ValueError(f"unknown session state {state!r}")
        with self._lock:
            old, self.state = self.state, state
        if old != state:
            self.events.write("state", state=state, previous=old, **({"reason": reason} if reason else {}))
            log.info("session state %s -> %s %s", old, state, reason)

    def incident(self, kind: str, message: str) -> None:
        """Something went wrong (and was handled, or not): events.jsonl, the health message and the summary."""
        rec = self.events.write("incident", kind=kind, message=message)
        with self._lock:
            self.incidents.append({k: rec[k] for k in ("time", "kind", "message")})
        self.summary.incidents.append(f"{rec['time']} {kind}: {message}")
        log.warning("incident %s: %s", kind, message)

    def announce_run(self, run_id: str, info: dict[str, Any], label: str = "") -> None:
        """The session records run ``run_id`` now ("" between runs): tell the tracker and the health message."""
        with self._lock:
            self.run = {"run_id": run_id, "label": label, **info} if run_id else {}
            self.position = {}
            self._announcement = run_announcement(session_id=self.session_id, run_id=run_id, run=info,
                                                  stamp=time.time())
        self._publish_announcement()

    def at_frame(self, frame: int, frames: int, episode: int) -> None:
        """Where the run is: ``frame`` of ``frames`` recorded, in episode file ``episode``."""
        self.position = {"frame": frame, "frames": frames, "episode": episode}

    # ------------------------------------------------------------ control, asked by capture
    def pause_requested(self) -> bool:
        """A pause was asked for and not yet resumed."""
        return self._pause.is_set()

    def take_skip(self) -> bool:
        """True once per ``ctl skip``: the current run should end as skipped."""
        if self._skip.is_set():
            self._skip.clear()
            return True
        return False

    def hold(self) -> None:
        """Paused: wait (state ``paused``) until resume, stop or skip; then back to ``running``."""
        self.set_state("paused")
        while self._pause.is_set() and not self.stop_event.is_set() and not self._skip.is_set():
            self._resume.wait(0.1)
        self._resume.clear()
        if not self.stop_event.is_set():
            self.set_state("running")

    def command(self, cmd: str) -> dict[str, Any]:
        """Apply a control command; the reply ``{"ok", "command", "state", "message"}``."""
        ok, msg = True, ""
        if cmd == "pause":
            self._pause.set()
            msg = "pausing at the end of the current episode" if self.state == "running" else "paused"
        elif cmd == "resume":
            ok = self._pause.is_set()
            msg = "resuming" if ok else "not paused"
            self._pause.clear()
            self._resume.set()
        elif cmd == "stop":
            self.stop_event.set()
            msg = "stopping after the current frame"
        elif cmd == "skip":
            ok = bool(self.run)
            if ok:
                self._skip.set()
                msg = f"skipping {self.run.get('label') or self.run.get('run_id')}"
            else:
                msg = "no run is being recorded"
        else:
            ok, msg = False, f"unknown command {cmd!r}; expected one of {COMMANDS}"
        self.events.write("ctl", command=cmd, ok=ok, message=msg)
        return {"ok": ok, "command": cmd, "state": self.state, "message": msg}

    def _on_ctl(self, query: Any) -> None:
        cmd = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            reply = self.command(cmd)
        except Exception as e:  # a reply always goes back
            reply = {"ok": False, "command": cmd, "state": self.state, "message": f"{type(e).__name__}: {e}"}
        query.reply(query.key_expr, encode_json(reply))

    # ------------------------------------------------------------ health
    def health(self) -> dict[str, Any]:
        """The health message now (rates over the last seconds, as last measured by the publisher)."""
        s = self.summary
        now = time.monotonic()
        wall = now - self._t0
        prog = self._progress()
        free = shutil.disk_usage(self.out_dir).free
        with self._lock:
            last = dict(self._last_health)
            run, pos, incidents, state = dict(self.run), dict(self.position), list(self.incidents), self.state
        eta = None
        if self.max_seconds and s.recorded_seconds > 0:
            eta = max(0.0, self.max_seconds - s.recorded_seconds) * wall / s.recorded_seconds
        elif prog.get("runs_done_here") and prog.get("runs_planned") is not None:
            left = prog["runs_planned"] - prog.get("runs_done", 0)
            eta = left * wall / prog["runs_done_here"]
        if pos.get("frames"):
            pos["fraction"] = round(pos["frame"] / pos["frames"], 4)
        if self.stop_event.is_set() and state in ("running", "paused", "initialising", "idle", "recovering"):
            state = "stopping"
        return {
            "schema": HEALTH_SCHEMA, "stamp": round(time.time(), 3), "session_id": self.session_id,
            "state": state, "out_dir": str(self.out_dir), "uptime_s": round(wall, 1),
            "run": run, "episode": pos,
            "progress": {**prog, "recorded_s": round(s.recorded_seconds, 2), "max_s": self.max_seconds,
                         "episodes_written": len(s.episodes)},
            "eta_s": None if eta is None else round(eta, 1),
            "camera": {"rate_hz": last.get("camera_hz"), "frames": s.frames_captured, "dropped": s.frames_dropped},
            "joint_states": {"rate_hz": last.get("state_hz"), "samples": s.state_samples},
            "worker": self._worker(),
            "keypoints": self._keypoints(),
            "disk": {"free_gb": round(free / 2**30, 3), "min_free_gb": self.min_free_gb,
                     "time_to_full_s": last.get("time_to_full_s")},
            "incidents": incidents,
        }

    def _measure(self) -> None:
        """Camera and joint-state rates and the disk's fill rate, sampled once a period."""
        now = time.monotonic()
        cam = self._cam_rate.update(now, self.summary.frames_captured)
        st = self._state_rate.update(now, self.summary.state_samples)
        free = shutil.disk_usage(self.out_dir).free
        drain = self._disk_rate.update(now, -free)  # bytes per s the free space shrinks
        ttf = None
        if drain is not None and drain > 0:
            ttf = round(max(0.0, free - self.min_free_gb * 2**30) / drain, 1)
        with self._lock:
            self._last_health = {"camera_hz": None if cam is None else round(cam, 2),
                                 "state_hz": None if st is None else round(st, 1), "time_to_full_s": ttf}

    def _publish_announcement(self) -> None:
        if self.bus is not None:
            try:
                self.bus.put(self.bus.key("session", "run"), encode_json(self._announcement))
            except Exception as e:
                log.debug("run announcement not sent: %s", e)

    def _publish_loop(self) -> None:
        assert self.bus is not None
        key = self.bus.key("health")
        while not self._stop_thread.is_set():
            try:
                self._measure()
                self.bus.put(key, encode_json(self.health()))
                self._publish_announcement()  # a worker that missed it (restarted, late) catches up
            except Exception as e:  # never let health reporting end the session
                log.warning("health message failed: %s", e)
            self._stop_thread.wait(self.period)
