"""Live keypoints into the recording: each message checked before anything is written, tracking gaps counted.

The session records a keypoint message only when it is well formed (``tdcommon.wire.check_keypoints``),
carries this session's id and the id of a run the session announced, and is of a frame the session
recorded in that run and has no keypoints for yet. Everything else is counted by kind and logged once
per kind, then at most once a minute (a flood of bad messages must not flood the log). The messages of a
watched run (the live initialisation's frames, never recorded) go to its watcher instead.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tdcommon.wire import check_keypoints

log = logging.getLogger(__name__)


class KindCounter:
    """Counts problems by kind; logs the first of a kind at once, then at most once per ``interval`` s."""

    def __init__(self, what: str, logger: logging.Logger, interval: float = 60.0,
                 on_first: Callable[[str, str], None] | None = None) -> None:
        self.what = what
        self.on_first = on_first  # called with (kind, detail) for the first problem of each kind
        self.log = logger
        self.interval = interval
        self.counts: dict[str, int] = {}
        self._logged: dict[str, tuple[float, int]] = {}  # kind -> (monotonic time logged, count then)
        self._lock = threading.Lock()

    def add(self, kind: str, detail: str) -> bool:
        """Count one problem of ``kind``; True when this call logged it (the first, or one a minute)."""
        now = time.monotonic()
        with self._lock:
            n = self.counts[kind] = self.counts.get(kind, 0) + 1
            last = self._logged.get(kind)
            if last is not None and now - last[0] < self.interval:
                return False
            self._logged[kind] = (now, n)
        since = "" if last is None else f" ({n - last[1]} more since the last report, {n} in all)"
        self.log.warning("%s: %s: %s%s", self.what, kind, detail, since)
        if last is None and self.on_first is not None:
            self.on_first(kind, detail)
        return True

    def total(self) -> int:
        """Problems counted over every kind."""
        with self._lock:
            return sum(self.counts.values())


@dataclass
class _Run:
    """Frames the session recorded in one run and the frames it accepted keypoints for."""

    frames: set[int] = field(default_factory=set)
    with_keypoints: set[int] = field(default_factory=set)
    started: float = field(default_factory=time.monotonic)  # host monotonic s
    newest_frame_stamp: float | None = None  # device s
    newest_keypoint_stamp: float | None = None  # device s


class KeypointGate:
    """Checks keypoint messages against what the session recorded; reports tracking coverage per episode.

    ``frame`` is called from the capture thread, ``accept`` from zenoh's callback thread.
    ``fps``: camera frames per second; ``gap_seconds``: a stretch of frames without keypoints at least this
    long (camera time) is a tracking gap.
    """

    def __init__(self, session_id: str, fps: float, gap_seconds: float, keep_runs: int = 2) -> None:
        self.session_id = session_id
        self.fps = fps
        self.gap_seconds = gap_seconds
        self.keep_runs = keep_runs  # keypoints of the previous run's last frames still land in its episodes
        self.rejected = KindCounter("keypoint message not recorded", log)
        self.accepted = 0
        self.last_accepted: float | None = None  # host monotonic s
        self.last_frame: float | None = None  # host monotonic s
        self.current_run = ""
        self._runs: OrderedDict[str, _Run] = OrderedDict()
        self._episode: list[tuple[int, float]] = []  # (frame number, device stamp s) of the open episode
        self._watched: dict[str, Callable[[dict[str, Any]], None]] = {}  # run id -> taker (not recorded)
        self._retired: OrderedDict[str, None] = OrderedDict()  # watched runs that ended: late messages dropped
        self.late_watched = 0  # messages of watched runs that came after the watch ended
        self._lock = threading.Lock()

    # ------------------------------------------------------------ capture side
    def begin_run(self, run_id: str) -> None:
        """Frames from now on belong to ``run_id`` ("" between runs); keypoints of the previous ``keep_runs - 1``
        runs still count; the same id again (a run continued after a pause or a fault) keeps what it had."""
        with self._lock:
            self.current_run = run_id
            if run_id and run_id not in self._runs:
                self._runs[run_id] = _Run()
            while len(self._runs) > self.keep_runs:
                self._runs.popitem(last=False)

    def frame(self, frame_number: int, stamp: float) -> None:
        """The session recorded ``frame_number`` (device ``stamp`` s) in the current run's open episode."""
        with self._lock:
            run = self._runs.get(self.current_run)
            if run is None:
                return
            run.frames.add(frame_number)
            run.newest_frame_stamp = stamp
            self._episode.append((frame_number, stamp))
            self.last_frame = time.monotonic()

    def episode_report(self) -> dict[str, Any]:
        """Tracking coverage of the episode being closed (keypoints received by now), and start the next.

        ``{"frames", "with_keypoints", "gaps", "gap_frames", "longest_gap_s"}``: ``gaps`` counts stretches of
        frames without keypoints lasting at least ``gap_seconds`` (the worker skips frames while busy; a
        gap means tracking stopped), ``gap_frames`` the frames inside them.
        """
        with self._lock:
            frames, self._episode = self._episode, []
            run = self._runs.get(self.current_run)
            got = run.with_keypoints if run is not None else set()
            fns = np.array([f for f, _ in frames], dtype=np.int64)
            stamps = np.array([s for _, s in frames], dtype=np.float64)
            has = np.isin(fns, np.fromiter(got, dtype=np.int64, count=len(got)))
        report = {"frames": int(len(fns)), "with_keypoints": int(has.sum()), "gaps": 0, "gap_frames": 0,
                  "longest_gap_s": 0.0, "gap_seconds": self.gap_seconds}
        if not len(fns) or has.all():
            return report
        edges = np.diff(np.concatenate([[1], has.astype(np.int8), [1]]))
        starts, ends = np.flatnonzero(edges == -1), np.flatnonzero(edges == 1) - 1  # inclusive stretches
        length = stamps[ends] - stamps[starts] + 1.0 / self.fps
        gap = length >= self.gap_seconds - 1e-9
        report.update(gaps=int(gap.sum()), gap_frames=int((ends - starts + 1)[gap].sum()),
                      longest_gap_s=round(float(length[gap].max()) if gap.any() else 0.0, 3))
        return report

    def watch(self, run_id: str, take: Callable[[dict[str, Any]], None] | None) -> None:
        """Hand the checked messages of run ``run_id`` (this session's, not recorded: the live initialisation)
        to ``take`` instead of rejecting them; ``take`` None stops it (the run's late messages are then dropped
        quietly: the worker answers the last frames after the session has moved on)."""
        with self._lock:
            if take is None:
                if self._watched.pop(run_id, None) is not None:
                    self._retired[run_id] = None
                    while len(self._retired) > 16:
                        self._retired.popitem(last=False)
            else:
                self._watched[run_id] = take

    def wait_keypoints(self, frame_number: int, timeout: float) -> bool:
        """Wait (wall time, at most ``timeout`` s) until keypoints of the current run's ``frame_number`` are
        accepted; False on timeout. Simulated time only: the camera does not pace the frames there."""
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                run = self._runs.get(self.current_run)
                if run is not None and frame_number in run.with_keypoints:
                    return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.002)

    # ------------------------------------------------------------ bus side
    def accept(self, payload: bytes) -> dict[str, Any] | None:
        """The decoded message when it may be recorded, else None (counted by kind and logged, rate-limited)."""
        try:
            msg = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as e:
            self.rejected.add("not_json", f"{type(e).__name__}: {e}")
            return None
        problem = check_keypoints(msg)
        if problem is not None:
            self.rejected.add(*problem)
            return None
        if msg["session_id"] != self.session_id:
            self.rejected.add("other_session", f"session {msg['session_id']!r}, this session is {self.session_id!r} "
                                               "(a worker left over from an earlier session?)")
            return None
        fn = msg["frame_number"]
        with self._lock:
            take = self._watched.get(msg["run_id"])
            late = take is None and msg["run_id"] in self._retired
            self.late_watched += late
        if take is not None:
            take(msg)
        if take is not None or late:
            return None
        with self._lock:
            run = self._runs.get(msg["run_id"])
            if run is None:
                kind, detail = "unknown_run", f"run {msg['run_id']!r} was not announced by this session recently"
            elif fn not in run.frames:
                kind, detail = "unknown_frame", f"frame {fn} was not recorded in run {msg['run_id']!r}"
            elif fn in run.with_keypoints:
                kind, detail = "duplicate", f"frame {fn} already has keypoints (two workers publishing?)"
            else:
                run.with_keypoints.add(fn)
                stamp = float(msg["stamp"])
                run.newest_keypoint_stamp = max(stamp, run.newest_keypoint_stamp or stamp)
                self.accepted += 1
                self.last_accepted = time.monotonic()
                return msg
        self.rejected.add(kind, detail)
        return None

    # ------------------------------------------------------------ health
    def lag_s(self) -> float | None:
        """Camera time by which the newest accepted keypoints trail the newest recorded frame of the current
        run (s); None before the run's first keypoints."""
        with self._lock:
            run = self._runs.get(self.current_run)
            if run is None or run.newest_frame_stamp is None or run.newest_keypoint_stamp is None:
                return None
            return max(0.0, run.newest_frame_stamp - run.newest_keypoint_stamp)

    def seconds_without_keypoints(self, since: float) -> float | None:
        """Host seconds since the last accepted keypoints (or ``since``, a monotonic time, if later) while
        frames are being recorded; None when no frame was recorded in the last 2 s (nothing to track)."""
        now = time.monotonic()
        with self._lock:
            if self.last_frame is None or now - self.last_frame > 2.0:
                return None
            run = self._runs.get(self.current_run)
            ref = max(since, self.last_accepted or since, run.started if run else since)
        return now - ref
