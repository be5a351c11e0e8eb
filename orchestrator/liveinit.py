"""The paper's per-object initialisation before recording, live: reference P0, a short move to P1, check.

Before an object's first recorded run the session (a) brings the arms to the run's start pose and lets
the object settle, (b) publishes frames at rest until the tracking worker has taken one as its reference
P0, (c) moves both grippers by ``tracking.live_init.displacement`` (ruckig-timed, safety-checked), holds
there (P1) and moves back, publishing every frame: the worker segments the object by differencing P1
against P0 and initialises, then tracks the move back; (d) checks the worker's keypoints of a frame at
rest after the move back: the keypoint count the object is configured for, an edge-length error below
``max_edge_error`` of the mean rest edge length and a keypoint within ``max_gripper_distance_m`` of each
closed gripper's TCP.
A failed check is retried (``attempts``); after the last one the object's runs are skipped (or, with
``on_failure: record``, recorded without it). None of these frames is recorded: they are announced on
``session/run`` as a run of their own (``phase: init``) with the ``track_id`` the object's recorded runs
then carry, so the worker keeps the initialised tracker into the recording (warm start) and the first
recorded frame is already tracked. In simulated time each frame waits for the worker's answer (the
camera does not pace the frames there).
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from drivers.base import DeviceError
from drivers.clock import Clock
from orchestrator.capture import EpisodeStream
from orchestrator.config import Config, LiveInitConfig
from orchestrator.live import KeypointGate
from orchestrator.plan import RunItem
from orchestrator.programs import EXECUTION_RATE
from orchestrator.progress import Progress
from orchestrator.station import ARMS, StatePoller, Station
from tdcommon.objects import default_keypoints

log = logging.getLogger(__name__)

TRACKED = ("init", "tracking")  # worker statuses of a usable result
PACE_TIMEOUT_S = 2.0  # simulated time: wall s a frame waits for the worker's answer before pacing stops


class InitFailed(RuntimeError):
    """One attempt failed; the message says why (no answer, not initialised, a check, a device fault)."""


class InitStopped(RuntimeError):
    """A stop request ended the initialisation."""


def expected_keypoints(category: str, n_keypoints: int | None) -> int:
    """The keypoint count the worker tracks for an object: ``n_keypoints`` (a cloth's as a square grid,
    as ``orchestrator.worker.tracking_params`` builds it) or the category's default."""
    n = n_keypoints or default_keypoints(category)
    if category == "cloth":
        side = max(2, int(round(np.sqrt(n))))
        return side * side
    return int(n)


def check_result(msgs: list[dict[str, Any]], expected: int, tcp: np.ndarray, closed: np.ndarray,
                 cfg: LiveInitConfig) -> tuple[str | None, dict[str, Any]]:
    """Check the worker's keypoint messages of frames at rest after the move back (oldest first): (why the
    initialisation fails or None, its metrics).

    Every message must be tracked (no ``lost`` or ``waiting``; at most half ``degraded``), the newest must
    hold ``expected`` keypoints with one within ``max_gripper_distance_m`` of each closed gripper, and the
    median edge-length RMSE (abs_mm) must be below ``max_edge_error`` times the newest message's mean rest
    edge length (``edge_error``, unitless, in the metrics). tcp: (2, 3) m world, left then
    right, the grippers' TCPs there (the arms at rest); closed: (2,) bool, the grippers holding the object.
    """
    if not msgs:
        return "no result from the worker", {}
    newest = msgs[-1]
    X = np.asarray([[p["x"], p["y"], p["z"]] if isinstance(p, dict) else p for p in newest.get("keypoints", [])],
                   np.float64).reshape(-1, 3)
    dist: dict[str, float] = {}
    if len(X):
        for k, arm in enumerate(ARMS):
            if closed[k]:
                dist[arm] = round(float(np.linalg.norm(X - tcp[k], axis=1).min()), 4)
    statuses = [str(m.get("status")) for m in msgs]
    abs_all = [m.get("abs_mm") for m in msgs]
    abs_ok = [a for a in abs_all if a is not None]
    cd_ok = [m["cd_mm"] for m in msgs if m.get("cd_mm") is not None]
    abs_mm = round(float(np.median(abs_ok)), 3) if abs_ok and len(abs_ok) == len(abs_all) else None
    rest = np.asarray(newest.get("rest_lengths") or [], np.float64)
    mean_rest_m = float(rest.mean()) if len(rest) else None
    ratio = round(abs_mm / 1e3 / mean_rest_m, 4) if abs_mm is not None and mean_rest_m else None
    metrics = {
        "frames": [m.get("frame_number") for m in msgs], "statuses": {s: statuses.count(s) for s in set(statuses)},
        "n_keypoints": int(len(X)), "expected_keypoints": expected, "abs_mm": abs_mm, "edge_error": ratio,
        "mean_rest_length_m": None if mean_rest_m is None else round(mean_rest_m, 5),
        "cd_mm": round(float(np.median(cd_ok)), 3) if cd_ok else None,
        "gripper_distance_m": dist, "grasp_indices": newest.get("grasp_indices"),
    }
    untracked = [s for s in statuses if s not in (*TRACKED, "degraded")]
    if untracked:
        note = f" ({newest['note']})" if newest.get("note") else ""
        return f"the worker is not tracking after the move (status {untracked[-1]}{note})", metrics
    degraded = statuses.count("degraded")
    if 2 * degraded > len(statuses):
        return f"the track is degraded in {degraded} of the {len(statuses)} checked frames", metrics
    if len(X) != expected:
        return f"{len(X)} keypoints, expected {expected}", metrics
    if ratio is None or not ratio < cfg.max_edge_error:
        return (f"edge-length error {abs_mm} mm = {ratio} of the mean edge length, must be below "
                f"{cfg.max_edge_error:g}"), metrics
    far = {a: d for a, d in dist.items() if d > cfg.max_gripper_distance_m}
    if far:
        what = ", ".join(f"{a} {d * 1e3:.0f} mm" for a, d in far.items())
        return (f"no keypoint at the closed gripper(s): nearest {what} "
                f"(max {cfg.max_gripper_distance_m * 1e3:.0f} mm)"), metrics
    return None, metrics


def plan_init_motions(station: Station, start: np.ndarray, cfg: LiveInitConfig) -> tuple[Any, Any]:
    """The approach to the start pose start (14,) rad (None when the arms are there) and the move out to
    the second configuration, the hold there and the move back, ruckig-timed and safety-checked:
    (approach, move) TimedPrograms. Raises InitFailed (before anything moves) when the displaced pose has
    no IK solution or the move breaks a limit."""
    from trajectories.ik import IKError, solve_ik
    from trajectories.program import Program, Waypoint
    from trajectories.safety import check_program
    from trajectories.timing import SAME_Q_TOL, SLOW, SpeedProfile, time_program

    start = np.asarray(start, np.float64).reshape(14)
    q = station.current_q()
    current = np.concatenate([q["left"], q["right"]])
    p1 = []
    for k, arm in enumerate(ARMS):
        qs = start[7 * k: 7 * k + 7]
        T = station.kin[arm].tcp_pose(qs).copy()
        T[:3, 3] += np.asarray(cfg.displacement, np.float64)
        try:
            p1.append(solve_ik(station.kin[arm], T, qs))
        except IKError as e:
            raise InitFailed(f"the {arm} gripper cannot reach the second configuration "
                             f"(displacement {list(cfg.displacement)} m): {e}") from None
    q1 = np.concatenate(p1)

    def waypoint(qq: np.ndarray, **kw: float) -> Waypoint:
        return Waypoint(left=qq[:7].tolist(), right=qq[7:].tolist(), **kw)

    approach = None
    if np.max(np.abs(current - start)) >= SAME_Q_TOL:
        approach = time_program(Program(name="live_init_approach", waypoints=[waypoint(start)]), SLOW,
                                current=current)
    move = time_program(Program(name="live_init", waypoints=[
        waypoint(start), waypoint(q1, duration=cfg.move_seconds, dwell=cfg.hold_seconds),
        waypoint(start, duration=cfg.move_seconds),
    ]), SpeedProfile("live_init", cfg.move_seconds))
    for timed in (approach, move):
        if timed is None:
            continue
        report = check_program(timed, station.bases)
        if report.violations:
            raise InitFailed("the initialisation move was refused before motion: "
                             + "; ".join(str(v) for v in report.violations[:3]))
    return approach, move


class _Answers:
    """The worker's keypoint messages of one initialisation run (from the gate's watch, zenoh's thread)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.newest: dict[str, Any] | None = None
        self.count = 0
        self.init_frame: int | None = None  # the frame the worker initialised on
        self.all: list[dict[str, Any]] = []

    def since(self, frame_number: int) -> list[dict[str, Any]]:
        """The messages of frames >= ``frame_number``, in frame order."""
        with self._cond:
            return sorted((m for m in self.all if m["frame_number"] >= frame_number),
                          key=lambda m: m["frame_number"])

    def add(self, msg: dict[str, Any]) -> None:
        with self._cond:
            self.all.append(msg)
            if self.newest is None or msg["frame_number"] >= self.newest["frame_number"]:
                if self.newest is None or self.newest["status"] != msg["status"]:
                    log.debug("live init: frame %d: %s %s", msg["frame_number"], msg["status"], msg.get("note", ""))
                    if msg["status"] == "init":
                        self.init_frame = int(msg["frame_number"])
                self.newest = msg
            self.count += 1
            self._cond.notify_all()

    def frame(self) -> int:
        """The newest answered frame number (-1 before any)."""
        with self._cond:
            return -1 if self.newest is None else int(self.newest["frame_number"])

    def wait_frame(self, frame_number: int, timeout: float) -> bool:
        """Wait (wall time) until a frame >= ``frame_number`` is answered; False on timeout."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while self.newest is None or self.newest["frame_number"] < frame_number:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True


@dataclass
class InitOutcome:
    """What an object's live initialisation did: ``ok`` with the track the runs carry, or the last reason."""

    object: str
    ok: bool
    track_id: str | None
    attempts: list[dict[str, Any]] = field(default_factory=list)
    reason: str | None = None
    seconds: float = 0.0
    stopped: bool = False
    worker_restarts: int = 0  # the supervisor's restart count when it succeeded (a restart later re-initialises)
    for_run: str = ""  # the label of the run it was done before
    finished: str = ""

    @property
    def metrics(self) -> dict[str, Any]:
        """The metrics of the last attempt's result (empty when it never got one)."""
        return dict(self.attempts[-1].get("metrics") or {}) if self.attempts else {}

    def meta(self, carried: bool) -> dict[str, Any]:
        """The episode metadata ``live_init``; ``carried``: a later run of the object kept this track."""
        return {"outcome": "ok" if self.ok else "failed", "attempts": len(self.attempts), "reason": self.reason,
                "seconds": round(self.seconds, 3), "metrics": self.metrics, "track_id": self.track_id,
                "before_run": self.for_run, "carried_over": carried, "finished": self.finished}

    def summary_line(self) -> str:
        """One line for the session summary."""
        n = len(self.attempts)
        head = f"{self.object}: {'ok' if self.ok else 'FAILED'} after {n} attempt{'s' if n != 1 else ''} " \
               f"({self.seconds:.1f} s)"
        if self.ok:
            m = self.metrics
            return head + (f": {m.get('n_keypoints')} keypoints, edge error {m.get('abs_mm')} mm "
                           f"({m.get('edge_error')} of an edge)")
        return head + f": {self.reason}"


class LiveInit:
    """Runs an object's initialisation on a connected station: ``LiveInit(...).run(station, item)``."""

    def __init__(self, config: Config, clock: Clock, stream: EpisodeStream, gate: KeypointGate,
                 stop_event: threading.Event, progress: Progress, state_rate: float,
                 set_state: Callable[[str, str], None] | None = None) -> None:
        self.config = config
        self.cfg = config.tracking.live_init
        self.clock = clock
        self.stream = stream
        self.gate = gate
        self.stop_event = stop_event
        self.progress = progress
        self.state_rate = state_rate
        self.set_state = set_state
        self.sim_time = config.clock == "sim"
        self.timeline: dict[str, Any] = {}  # the last attempt's phase frame numbers
        self._last = -1

    def run(self, station: Station, item: RunItem, worker_restarts: Callable[[], int] = lambda: 0) -> InitOutcome:
        """Attempt the initialisation up to ``attempts`` times before ``item`` (the object's next run)."""
        from orchestrator.journal import now_iso
        from trajectories.program import ProgramError, load_program, resolve_program

        obj = item.object
        out = InitOutcome(obj.name, False, None, for_run=item.label)
        t0 = time.monotonic()
        try:
            start = load_program(resolve_program(item.program)).q()[0]  # the run's first waypoint
        except ProgramError as e:
            out.reason = f"no start pose: {e}"
            out.finished = now_iso()
            return out
        expected = expected_keypoints(obj.category, obj.n_keypoints)
        for attempt in range(1, self.cfg.attempts + 1):
            if self.stop_event.is_set():
                out.stopped = True
                break
            restarts = worker_restarts()
            if self.set_state is not None:
                self.set_state("initialising",
                               f"{obj.name}: live initialisation, attempt {attempt}/{self.cfg.attempts}")
            ta = time.monotonic()
            rec: dict[str, Any] = {"attempt": attempt}
            track = uuid.uuid4().hex[:12]
            try:
                self.timeline = {}
                msgs, tcp, closed = self._attempt(station, item, start, track)
                reason, metrics = check_result(msgs, expected, tcp, closed, self.cfg)
                rec["metrics"] = {**metrics, "timeline": self.timeline}
                if reason is None and worker_restarts() != restarts:
                    reason = "the tracking worker restarted during the initialisation"
            except InitFailed as e:
                reason = str(e)
            except InitStopped:
                out.stopped = True
                rec.update(outcome="stopped", seconds=round(time.monotonic() - ta, 3))
                out.attempts.append(rec)
                break
            rec.update(outcome="ok" if reason is None else "failed", reason=reason,
                       seconds=round(time.monotonic() - ta, 3))
            out.attempts.append(rec)
            if reason is None:
                out.ok, out.track_id, out.reason, out.worker_restarts = True, track, None, restarts
                break
            out.reason = reason
            msg_txt = f"{obj.name}: live initialisation attempt {attempt}/{self.cfg.attempts} failed: {reason}"
            log.warning(msg_txt)
            self.progress.message(f"warning: {msg_txt}")
            if station.broken:
                break
        if out.stopped:
            out.reason = "stopped"
        out.seconds = time.monotonic() - t0
        out.finished = now_iso()
        return out

    # ------------------------------------------------------------------ one attempt
    def _attempt(self, station: Station, item: RunItem, start: np.ndarray,
                 track: str) -> tuple[list[dict[str, Any]], np.ndarray, np.ndarray]:
        """Approach, P0, move out / hold / back, settle; the worker's answers for ``check_frames`` frames at
        rest afterwards, with the TCPs (2, 3) m and closed flags (2,) there. ``timeline`` gets the frame
        numbers of the phases and where the worker initialised."""
        stream, cfg = self.stream, self.cfg
        approach, move = plan_init_motions(station, start, cfg)
        run_id = f"init-{uuid.uuid4().hex[:12]}"
        answers = _Answers()
        self.gate.watch(run_id, answers.add)
        obj = item.object
        stream.last_frame_number = None
        stream.begin_init(run_id, {
            "object": obj.name, "category": obj.category, "program": item.program, "speed": item.speed,
            "run_index": item.index, "n_keypoints": obj.n_keypoints, "phase": "init", "track_id": track,
        }, f"{obj.name} · live initialisation")
        poller = None if self.sim_time else StatePoller(lambda: stream.publish_states(station), self.state_rate)
        self._next_state_t = self.clock.now()
        self._pace = self.sim_time
        self._last = -1  # the newest frame number read
        try:
            if poller:
                poller.__enter__()
            if approach is not None:
                self._move(station, approach, answers, publish=False)
            self._rest(station, cfg.settle_seconds, answers, publish=False)
            # P0: frames at rest until the worker has taken one as its reference
            stream.run_info["init_step"] = "p0"
            deadline = time.monotonic() + cfg.worker_timeout_s
            while answers.count == 0:
                if time.monotonic() > deadline:
                    raise InitFailed("the tracking worker answered no reference frame within "
                                     f"{cfg.worker_timeout_s:g} s")
                self._frame(station, answers, publish=True)
            phases = {"p0": int(answers.since(-1)[0]["frame_number"])}
            hold_t = float(move.waypoint_times()[1])  # the arrival at P1, s after the move started
            self._move(station, move, answers, publish=True, mark=(hold_t, phases))
            phases["back_at_start"] = self._last
            stream.run_info["init_step"] = "rest"
            self._rest(station, cfg.settle_seconds, answers, publish=True)
            last = self._last + 1  # the frames read from now on are checked
            deadline = time.monotonic() + cfg.worker_timeout_s
            while len(answers.since(last)) < cfg.check_frames:  # results of frames at rest after the move back
                if time.monotonic() > deadline:
                    raise InitFailed(f"the tracking worker reported {len(answers.since(last))} of "
                                     f"{cfg.check_frames} results within {cfg.worker_timeout_s:g} s "
                                     "after the move back")
                newest = answers.newest
                if newest is not None and newest["frame_number"] >= last and newest["status"] not in (
                        *TRACKED, "degraded"):
                    break  # not tracking at rest: it will not initialise any more (no difference to P0)
                self._frame(station, answers, publish=True)
            msgs = answers.since(last)[: cfg.check_frames]
            q = station.current_q()
            tcp = np.stack([station.kin[a].tcp_pose(q[a])[:3, 3] for a in ARMS])
            closed = np.array([station.grippers[a].read_state().grasped for a in ARMS])
            init = answers.init_frame
            self.timeline = {**phases, "checked_from": last, "initialised_at": init,
                             "initialised_during": None if init is None else
                             "move out" if init < phases.get("p1", 1 << 62) else
                             "hold at P1" if init <= phases.get("back", 1 << 62) else
                             "move back" if init <= phases["back_at_start"] else "rest"}
            return msgs, tcp, closed
        except DeviceError as e:
            station.stop_arms()
            if not e.recoverable:
                station.broken = str(e)
                raise InitFailed(f"device fault: {e}") from None
            try:
                station.recover()
            except DeviceError as e2:
                station.broken = f"recovery failed: {e2}"
                raise InitFailed(f"device fault: {e}; recovery failed: {e2}") from None
            raise InitFailed(f"device fault: {e} (recovered)") from None
        except (InitFailed, InitStopped):
            station.stop_arms()
            raise
        finally:
            if poller:
                poller.__exit__(None, None, None)
            self.gate.watch(run_id, None)
            stream.begin_init("", {}, "")

    def _frame(self, station: Station, answers: _Answers, publish: bool) -> int:
        """Read (and publish) one frame, joint states sampled up to it in simulated time; its frame number."""
        if self.stop_event.is_set():
            raise InitStopped
        if self.sim_time:
            t_next = self.clock.now() + 1.0 / station.fps
            while self._next_state_t < t_next:
                self.clock.sleep_until(self._next_state_t)
                self.stream.publish_states(station)
                self._next_state_t += 1.0 / self.state_rate
        frame = station.read_frame()
        self._last = frame.frame_number
        if publish:
            self.stream.publish_frame(frame, station)
            if self._pace and not answers.wait_frame(frame.frame_number, PACE_TIMEOUT_S):
                self._pace = False  # a worker this slow fails the attempt on its own timeouts
        return frame.frame_number

    def _rest(self, station: Station, seconds: float, answers: _Answers, publish: bool) -> int:
        """Frames for ``seconds`` with the arms at rest; the last frame number (-1 for none)."""
        last = -1
        for _ in range(round(seconds * station.fps)):
            last = self._frame(station, answers, publish)
        return last

    def _move(self, station: Station, timed: Any, answers: _Answers, publish: bool,
              mark: tuple[float, dict[str, int]] | None = None) -> None:
        """Run a timed motion on both arms, reading (and publishing) frames until it ends. ``mark``: (the
        arrival at P1, s after the start; a dict that gets the frame numbers ``p1`` and ``back`` there); each
        frame's header then says ``init_step`` move, p1 or back (the worker initialises at P1, not on the way)."""
        left, right = timed.to_motions(EXECUTION_RATE)
        t0 = self.clock.now()
        station.arms["left"].start_motion(left)
        station.arms["right"].start_motion(right)
        while self.clock.now() - t0 < timed.duration:
            if mark is not None:
                t = self.clock.now() - t0
                step = "move" if t < mark[0] else "p1" if t < mark[0] + self.cfg.hold_seconds else "back"
                self.stream.run_info["init_step"] = step
                mark[1].setdefault(step, self._last + 1)
            self._frame(station, answers, publish)
            for arm in station.arms.values():
                arm.wait_motion(0.0)  # raises DeviceError on a fault
        for arm in station.arms.values():
            if not arm.wait_motion(timeout=max(1.0, timed.duration)):
                raise DeviceError("arm did not finish the initialisation move in time")
