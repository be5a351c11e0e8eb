"""A collection session: run the plan on the station, record 5 s episodes, publish on the bus.

One loop drives everything from the camera: each frame is read, recorded and published; the
arms' joint states are sampled at ``state_rate`` in between (a thread in real time, inline in
simulated time, so a simulated run is deterministic and as fast as the CPU allows).
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from itertools import groupby
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import Arm, DeviceError, Gripper, RGBDCamera, create_arm, create_camera, create_gripper
from drivers.clock import Clock
from drivers.types import RGBDFrame
from orchestrator import __version__
from orchestrator.bus import Bus
from orchestrator.config import Config, ObjectConfig
from orchestrator.journal import Journal, RunKey, key_fields, now_iso, record_key, run_key
from orchestrator.plan import RunItem, build_plan
from orchestrator.programs import ProgramRejected, plan_motion
from orchestrator.progress import Progress
from orchestrator.recorder import Recorder, recover_active
from orchestrator.wire import decode_json, encode_frame, encode_json
from trajectories.kinematics import PandaKinematics, pose_to_input

log = logging.getLogger(__name__)
ARMS = ("left", "right")


@dataclass
class SessionSummary:
    """What a session did; printed at the end and written as ``summary.json``."""

    out_dir: Path
    episodes: list[Path] = field(default_factory=list)
    frames_captured: int = 0
    frames_dropped: int = 0
    state_samples: int = 0
    keypoints_recorded: int = 0
    runs_done: int = 0
    runs_failed: list[str] = field(default_factory=list)
    runs_cut_short: list[str] = field(default_factory=list)  # counted in runs_done; not journaled, so re-run
    runs_planned: int = 0  # run items in one pass over the plan
    runs_already_done: int = 0  # skipped: done in an earlier session (the journal says so)
    plan_runs_done: int = 0  # runs of the current pass done by the end, earlier sessions included
    plan_pass: int = 0
    journal: str | None = None
    faults_recovered: int = 0
    start_skew_s: float = 0.0  # largest delay between the two arms' motion starts over the runs, s
    errors: list[str] = field(default_factory=list)
    recorded_seconds: float = 0.0
    wall_seconds: float = 0.0
    stopped_early: str | None = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dict."""
        d = asdict(self)
        d["out_dir"] = str(self.out_dir)
        d["episodes"] = [str(p) for p in self.episodes]
        return d

    def text(self) -> str:
        """The human summary printed at the end of a session."""
        lines = [
            f"episodes written : {len(self.episodes)}",
            f"frames captured  : {self.frames_captured}",
            f"frames dropped   : {self.frames_dropped}",
            f"joint states     : {self.state_samples}",
            f"keypoint sets    : {self.keypoints_recorded}",
            f"program runs     : {self.runs_done} done, {len(self.runs_failed)} failed"
            + (f" ({len(self.runs_cut_short)} of the done cut short by the stop: re-run from the start on resume)"
               if self.runs_cut_short else ""),
            f"arm start skew   : {self.start_skew_s * 1e3:.3f} ms (largest over the runs)",
            f"recorded         : {self.recorded_seconds:.1f} s in {self.wall_seconds:.1f} s",
            f"output           : {self.out_dir}",
        ]
        if self.runs_already_done:
            lines.append(f"resumed          : {self.runs_already_done} of {self.runs_planned} runs were done "
                         f"by earlier sessions (journal {self.journal}); not run again")
        if self.runs_planned:
            pass_txt = f" (pass {self.plan_pass + 1})" if self.plan_pass else ""
            lines.append(f"plan progress    : {self.plan_runs_done} of {self.runs_planned} runs done{pass_txt}")
        for label in self.runs_cut_short:
            lines.append(f"cut short        : {label}")
        if self.faults_recovered:
            lines.append(f"faults recovered : {self.faults_recovered}")
        if self.stopped_early:
            lines.append(f"stopped early    : {self.stopped_early}")
        for e in self.errors + self.runs_failed:
            lines.append(f"problem          : {e}")
        return "\n".join(lines)


class Station:
    """The station's devices for one object (in mock mode, a simulated station holding that object)."""

    def __init__(self, config: Config, obj: ObjectConfig, clock: Clock) -> None:
        st = config.station
        self.clock = clock
        self.sim: Any = None
        context: dict[str, Any] = {"clock": clock}
        if st.simulated:
            from drivers.fake.devices import SimStation

            assert obj.sim is not None  # guaranteed by Config validation
            self.sim = SimStation(obj.sim, clock, n_keypoints=obj.n_keypoints)
            context["station"] = self.sim
        slots = {"left": st.left, "right": st.right}
        self.arms: dict[str, Arm] = {n: create_arm(s.arm, name=n, **context) for n, s in slots.items()}
        self.grippers: dict[str, Gripper] = {
            n: create_gripper(s.gripper, name=n, **context, **self._gripper_context(s)) for n, s in slots.items()
        }
        self.camera: RGBDCamera = create_camera(st.camera, **context)
        self.kin = {n: PandaKinematics(s.arm.base.matrix()) for n, s in slots.items()}
        self.bases = {n: s.arm.base.matrix() for n, s in slots.items()}
        self.T_world_cam = st.camera.pose.matrix()
        self.fps = st.camera.fps
        self.broken: str | None = None  # set after a fault that needs a person; no more runs here
        self._connected: list[Any] = []

    @staticmethod
    def _gripper_context(slot: Any) -> dict[str, Any]:
        """A Franka Hand talks to the controller of the arm it is mounted on."""
        return {"arm_config": slot.arm} if slot.gripper.type == "franka_hand" else {}

    def connect(self, retries: int = 3) -> None:
        """Connect every device (retrying device faults); raise DeviceError naming the one that failed."""
        devices: list[tuple[str, Any]] = [
            *((f"{n} arm", a) for n, a in self.arms.items()),
            *((f"{n} gripper", g) for n, g in self.grippers.items()),
            ("camera", self.camera),
        ]
        for label, dev in devices:
            for attempt in range(1, retries + 1):
                try:
                    dev.connect()
                    self._connected.append(dev)
                    break
                except DeviceError as e:
                    if attempt == retries or not e.recoverable:
                        raise DeviceError(f"{label}: could not connect after {attempt} attempts: {e}") from e
                    log.warning("%s: connect failed (%s), retrying", label, e)
                    time.sleep(0.5 * attempt)

        recorded_pose = getattr(self.camera, "T_world_cam", None)  # a replay brings its recording's pose
        if recorded_pose is not None:
            self.T_world_cam = np.asarray(recorded_pose, dtype=np.float64)

    def close(self) -> None:
        """Close every connected device, in reverse order, whatever happens."""
        for dev in reversed(self._connected):
            try:
                dev.close()
            except Exception as e:
                log.warning("closing %r failed: %s", dev, e)
        self._connected.clear()

    def sample_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """Both arms' joint states, gripper states and u_t (12,) as the ``arms/state`` message, plus TCP poses."""
        msg: dict[str, Any] = {}
        u, tcps = [], {}
        for n in ARMS:
            js = self.arms[n].read_state()
            gs = self.grippers[n].read_state()
            T = self.kin[n].tcp_pose(js.q)
            tcps[f"{n}_tcp"] = T
            u.append(pose_to_input(T))
            msg[n] = {
                "stamp": js.stamp, "q": js.q.tolist(), "dq": js.dq.tolist(),
                "gripper_width": gs.width, "grasped": gs.grasped,
            }
        msg["stamp"] = msg["left"]["stamp"]
        msg["u"] = np.concatenate(u).tolist()
        return msg, tcps

    def current_q(self) -> dict[str, np.ndarray]:
        """(7,) joint vector of each arm now."""
        return {n: self.arms[n].read_state().q for n in ARMS}


@dataclass
class _Resume:
    """Where a program run continues after a recovered fault: a waypoint and the next chunk index."""

    waypoint: int = 0
    chunk: int = 0


class _StatePoller:
    """Samples joint states at ``rate`` Hz on a thread (real time only)."""

    def __init__(self, sample: Callable[[], None], rate: float) -> None:
        self._sample, self._period = sample, 1.0 / rate
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="state-poller", daemon=True)
        self.errors: list[str] = []

    def _run(self) -> None:
        t = time.monotonic()
        while not self._stop.is_set():
            try:
                self._sample()
            except Exception as e:
                self.errors.append(f"joint state sampling: {type(e).__name__}: {e}")
                log.warning("joint state sampling failed: %s", e)
            t += self._period
            delay = t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                t = time.monotonic()  # fell behind: do not burst

    def __enter__(self) -> _StatePoller:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2.0)


class Session:
    """Runs a plan: ``Session(config, out_dir, clock).run()``."""

    def __init__(
        self,
        config: Config,
        out_dir: Path,
        clock: Clock,
        *,
        bus: Bus | None = None,
        progress: Progress | None = None,
        stop_event: threading.Event | None = None,
        state_rate: float = 250.0,
        on_station: Callable[[Station], None] | None = None,
        journal: Journal | None = None,
    ) -> None:
        self.config = config
        self.out_dir = Path(out_dir)
        self.clock = clock
        self.sim_time = config.clock == "sim"
        self.bus = bus
        self.progress = progress or Progress(enabled=False)
        self.stop_event = stop_event or threading.Event()
        self.state_rate = state_rate
        self.on_station = on_station  # called with each station right after it connects (tests inject faults)
        self.summary = SessionSummary(self.out_dir)
        self._episode_index = 0
        self._recorder: Recorder | None = None
        self._frame_key = ""
        self._state_key = ""
        self._max_seconds: float | None = None
        self._last_frame_number: int | None = None
        self._run_info: dict[str, Any] = {}
        self._episode_open = False
        self._journal = journal  # opened by the caller (the CLI checks it early), else by run(); closed by run()
        self._pass = 0
        self._session_index = 0
        self._session_started = ""
        self._attempts: dict[RunKey, int] = {}
        self._attempt = 1
        self._item_episodes: list[Path] = []
        self._pending: list[tuple[dict[str, Any], list[Path]]] = []  # "done" records waiting for their files
        self._done_keys: set[RunKey] = set()

    # ------------------------------------------------------------------ public
    def run(self, max_seconds: float | None = None, loop: bool = False) -> SessionSummary:
        """Run the plan once (or repeatedly with ``loop``) until done, stopped or ``max_seconds`` recorded.

        The folder's journal says which runs earlier sessions finished: those are skipped, the
        rest run in plan order. Raises JournalError (before touching the folder) for another plan's journal.
        """
        t_wall = time.monotonic()
        self._max_seconds = max_seconds
        self.out_dir.mkdir(parents=True, exist_ok=True)
        journal = self._journal
        if journal is None or journal.closed:
            journal = self._journal = Journal.open(self.out_dir, self.config)
        try:
            for path, outcome in recover_active(self.out_dir):
                self.progress.message(f"found an unfinished episode from an earlier run: {path.name}: {outcome}")
            self._episode_index = self._next_episode_index()
            cam = self.config.station.camera
            out = self.config.output
            self._recorder = Recorder(cam.id, out.compression, color=out.color, depth=out.depth)
            if self.bus is not None:
                self._frame_key = self.bus.key("cam", cam.id, "frame")
                self._state_key = self.bus.key("arms", "state")
                self.bus.subscribe(self.bus.key("keypoints"), callback=self._on_keypoints)
            items = build_plan(self.config.plan)
            self._run_plan(items, journal, loop)
        finally:
            self._finish(journal, t_wall)
        return self.summary

    def _run_plan(self, items: list[RunItem], journal: Journal, loop: bool) -> None:
        """Run the plan's items the journal does not list as done, pass after pass with ``loop``."""
        state = journal.state()
        self._pass, self._attempts, self._done_keys = state.pass_index, dict(state.attempts), set(state.done)
        self._session_index, self._session_started = state.sessions, now_iso()
        planned = {run_key(it) for it in items}
        self.summary.runs_planned = len(items)
        self.summary.journal = journal.path.name
        journal.append({"type": "session", "index": self._session_index, "started": self._session_started,
                        "software": __version__, "runs_planned": len(items), "loop": loop})
        all_done = planned <= self._done_keys
        msg = ""
        if all_done and loop:
            msg = (f"resuming: pass {self._pass + 1} over the plan is complete ({len(items)} run(s)); "
                   f"starting pass {self._pass + 2}")
            self._next_pass()
        elif all_done:
            self.summary.runs_already_done = len(items)
            msg = (f"resuming: all {len(items)} run(s) of the plan are already done in {self.out_dir} "
                   f"(journal {journal.path.name}); nothing left to do. --fresh records the plan again")
        elif self._done_keys & planned or state.interrupted & planned:
            self.summary.runs_already_done = len(self._done_keys & planned)
            first = next(it for it in items if run_key(it) not in self._done_keys)
            again = ""
            if run_key(first) in state.interrupted:
                again = (f" (attempt {self._attempts.get(run_key(first), 0) + 1}: an earlier attempt was cut short; "
                         "its episodes stay and this one starts the run over)")
            msg = (f"resuming: {self.summary.runs_already_done} of {len(items)} runs already done, "
                   f"continuing with {first.label}{again}")
        if msg:
            log.info(msg)
            self.progress.message(msg)
        if all_done and not loop:
            return
        try:
            while not self._should_stop():
                todo = [it for it in items if run_key(it) not in self._done_keys]
                recorded_before = self.summary.recorded_seconds
                for _name, group in groupby(todo, key=lambda it: it.object.name):
                    if self._should_stop():
                        break
                    self._run_object(list(group))
                if not loop:
                    break
                if self.summary.recorded_seconds == recorded_before and not self._should_stop():
                    self.summary.stopped_early = "a whole pass over the plan recorded nothing"
                    break
                if not self._should_stop():
                    self._next_pass()
        except KeyboardInterrupt:
            self.summary.stopped_early = "interrupted"

    def _next_pass(self) -> None:
        """Start another pass over the plan (``loop``): every item is to do again, attempts count from 1."""
        self._flush_pending(final=False)
        self._pass += 1
        self._attempts, self._done_keys = {}, set()

    def _finish(self, journal: Journal, t_wall: float) -> None:
        """Finish the episodes, journal the runs whose files are now final, fill and write the summary."""
        try:
            if self._recorder is not None:
                self._recorder.stop()
                self._flush_pending(final=True)
                self.summary.episodes = sorted(self._recorder.finished)
                self.summary.keypoints_recorded = self._recorder.keypoints_written
                self.summary.errors.extend(self._recorder.errors)
        finally:
            journal.close()
        planned = {run_key(it) for it in build_plan(self.config.plan)}
        self.summary.plan_runs_done = len(self._done_keys & planned)
        self.summary.plan_pass = self._pass
        self.summary.wall_seconds = time.monotonic() - t_wall
        self.progress.done()
        (self.out_dir / "summary.json").write_text(json.dumps(self.summary.to_dict(), indent=2))

    # ------------------------------------------------------------------ internals
    def _next_episode_index(self) -> int:
        """Continue numbering after the episodes already in the folder or its quarantine (a resumed session)."""
        idx = []
        for p in [*self.out_dir.glob("episode_*.mcap*"), *self.out_dir.glob("quarantine/episode_*.mcap*")]:
            number = p.name.split("_")[1].split(".")[0]
            if number.isdigit():
                idx.append(int(number))
        return max(idx) + 1 if idx else 0

    def _should_stop(self) -> bool:
        if self.stop_event.is_set():
            self.summary.stopped_early = self.summary.stopped_early or "stop requested"
            return True
        if self._max_seconds is not None and self.summary.recorded_seconds >= self._max_seconds - 1e-6:
            return True
        return False

    def _on_keypoints(self, sample: Any) -> None:
        try:
            msg = decode_json(sample.payload.to_bytes())
        except Exception as e:
            log.warning("ignored a malformed keypoint message: %s", e)
            return
        if self._recorder is not None:
            self._recorder.keypoints(msg)

    def _run_object(self, items: list[RunItem]) -> None:
        obj = items[0].object
        station = Station(self.config, obj, self.clock)
        try:
            station.connect()
        except DeviceError as e:
            self.summary.errors.append(f"{obj.name}: station not ready: {e}")
            self.progress.message(f"error: {obj.name}: {e}")
            station.close()
            for item in items:  # journaled so the record says why; retried on resume like a failed run
                self._journal_run(item, "skipped", f"station not ready: {e}", [], 0.0)
            return
        try:
            if self.on_station is not None:
                self.on_station(station)
            for item in items:
                if self._should_stop():
                    break
                if station.broken:
                    reason = f"skipped, the station needs attention ({station.broken})"
                    self.summary.runs_failed.append(f"{item.label}: {reason}")
                    self._journal_run(item, "skipped", reason, [], 0.0)
                    continue
                self._run_journaled(item, station)
        finally:
            station.close()

    def _run_journaled(self, item: RunItem, station: Station) -> None:
        """Run an item between a ``start`` and a ``run`` journal record (none when a stop cuts it short)."""
        key = run_key(item)
        self._flush_pending(final=False)
        self._attempt = self._attempts.get(key, 0) + 1
        self._attempts[key] = self._attempt
        assert self._journal is not None
        self._journal.append({
            "type": "start", "pass": self._pass, **key_fields(key), "attempt": self._attempt,
            "session": self._session_index, "first_episode": self._episode_index, "started": now_iso(),
        })
        self._item_episodes = []
        t0 = time.monotonic()
        outcome, reason = self._run_item_with_retries(item, station)
        episodes, wall = list(self._item_episodes), time.monotonic() - t0
        if outcome == "stopped":
            self.summary.runs_cut_short.append(
                f"{item.label}: stopped after {len(episodes)} episode(s); runs again from its start on resume"
            )
        elif outcome == "done":  # journaled once its files are final (the recorder closes them behind capture)
            self._done_keys.add(key)
            self._pending.append((self._run_record(item, "done", None, episodes, wall), episodes))
        else:
            self._journal_run(item, outcome, reason, episodes, wall)

    def _run_record(
        self, item: RunItem, outcome: str, reason: str | None, episodes: list[Path], wall: float
    ) -> dict[str, Any]:
        """The ``run`` journal record of a finished item."""
        return {
            "type": "run", "pass": self._pass, **key_fields(run_key(item)), "outcome": outcome,
            "reason": reason, "attempt": self._attempts.get(run_key(item), 0), "session": self._session_index,
            "episodes": [p.name for p in episodes], "wall_seconds": round(wall, 3), "finished": now_iso(),
        }

    def _journal_run(self, item: RunItem, outcome: str, reason: str | None, episodes: list[Path],
                     wall: float) -> None:
        """Journal a failed or skipped item now (it is retried on resume whatever its files' state)."""
        assert self._journal is not None
        self._journal.append(self._run_record(item, outcome, reason, episodes, wall))

    def _flush_pending(self, final: bool) -> None:
        """Journal the "done" runs whose episode files are all final; with ``final``, the rest as failed."""
        if not self._pending or self._recorder is None or self._journal is None:
            return
        finished = set(self._recorder.finished)
        keep = []
        for record, episodes in self._pending:
            missing = [p.name for p in episodes if p not in finished]
            if not missing:
                self._journal.append(record)
            elif final:
                self._journal.append({**record, "outcome": "failed",
                                      "reason": f"episode file(s) not finished: {', '.join(missing)}"})
                self._done_keys.discard(record_key(record))
            else:
                keep.append((record, episodes))
        self._pending = keep

    def _run_item_with_retries(self, item: RunItem, station: Station, retries: int = 2) -> tuple[str, str | None]:
        """Run an item; after a recoverable fault, recover and retry the faulted segment at slow speed.

        Returns ("done" | "stopped" | "failed", the failure message or None).
        """
        resume = _Resume()
        for attempt in range(retries + 1):
            try:
                complete = self._run_item(item, station, resume)
                self.summary.runs_done += 1
                return ("done", None) if complete else ("stopped", None)
            except DeviceError as e:
                msg = f"{item.label}: device fault: {e}"
                log.warning(msg)
                self.progress.message(f"warning: {msg}")
                self._stop_arms(station)
                if not e.recoverable or attempt == retries:
                    self.summary.runs_failed.append(msg)
                    if not e.recoverable:
                        station.broken = str(e)
                    return "failed", msg
                try:
                    self._recover(station)
                except DeviceError as e2:
                    self.summary.runs_failed.append(f"{msg}; recovery failed: {e2}")
                    station.broken = f"recovery failed: {e2}"
                    return "failed", f"{msg}; recovery failed: {e2}"
                self.summary.faults_recovered += 1
                self.progress.message(
                    f"recovered; retrying from waypoint {resume.waypoint} (approach at slow speed)"
                )
            except ProgramRejected as e:
                self.summary.runs_failed.append(f"{item.label}: {e}")
                self.progress.message(f"error: {item.label}: {e}")
                return "failed", f"{item.label}: {e}"
        return "failed", f"{item.label}: no attempt left"  # not reached: the last attempt returns above

    @staticmethod
    def _stop_arms(station: Station) -> None:
        """Stop every arm, ignoring arms that cannot (a faulted arm is already stopped)."""
        for arm in station.arms.values():
            try:
                arm.stop()
            except DeviceError as e:
                log.warning("stop after a fault: %s", e)

    @staticmethod
    def _recover(station: Station) -> None:
        """Clear recoverable faults on every arm; raises DeviceError when one cannot be cleared."""
        for arm in station.arms.values():
            arm.recover()

    def _sample_states(self, station: Station) -> None:
        msg, tcps = station.sample_state()
        self.summary.state_samples += 1
        assert self._recorder is not None
        self._recorder.arm_state(msg, tcps)
        if self.bus is not None:
            self.bus.put(self._state_key, encode_json(msg))

    def _read_frame(self, station: Station, retries: int = 3) -> RGBDFrame:
        last: DeviceError | None = None
        for attempt in range(retries):
            try:
                return station.camera.read(timeout=2.0)
            except DeviceError as e:
                last = e
                log.warning("camera read failed (%s), attempt %d/%d", e, attempt + 1, retries)
        try:  # reconnect once before giving up
            station.camera.close()
            station.camera.connect()
            return station.camera.read(timeout=2.0)
        except DeviceError as e:
            raise DeviceError(f"camera: no frame after {retries} attempts and a reconnect: {last}; {e}") from e

    def _run_item(self, item: RunItem, station: Station, resume: _Resume) -> bool:
        """Record one program run (from ``resume.waypoint`` after a fault) as whole episodes.

        Returns False when a stop (signal, ``max_seconds``, low disk) cut the run short.
        On a DeviceError, ``resume`` is updated with the waypoint to retry from and the next chunk index.
        """
        assert self._recorder is not None
        plan = self.config.plan
        motion = plan_motion(item, station, plan.fast_duration, start_waypoint=resume.waypoint)
        fps = station.fps
        per_episode = max(1, round(plan.episode_seconds * fps))
        settle_frames = round(plan.settle_seconds * fps) if resume.waypoint == 0 else 0
        total = math.ceil((settle_frames + motion.duration * fps) / per_episode) * per_episode
        events = list(motion.gripper_events)
        t_start: float | None = None
        chunk = resume.chunk - 1
        episode_frames = 0
        frames = 0
        base_meta = self._base_metadata(item, station, motion)
        base_meta["start_waypoint"] = resume.waypoint
        self._last_frame_number = None  # frames the camera made between runs were not meant to be recorded
        self._run_info = {
            "object": item.object.name, "category": item.object.category, "program": item.program,
            "speed": item.speed, "run_index": item.index, "n_keypoints": item.object.n_keypoints,
        }
        poller = None if self.sim_time else _StatePoller(lambda: self._sample_states(station), self.state_rate)
        next_state_t = self.clock.now()
        try:
            if poller:
                poller.__enter__()
            for k in range(total):
                if k % per_episode == 0:
                    if chunk >= 0:
                        self._close_episode(station, episode_frames == per_episode)
                    if self._should_stop():
                        break
                    chunk += 1
                    episode_frames = 0
                    self._open_episode({**base_meta, "chunk_index": chunk})
                if k == settle_frames:
                    t_start = self._start_motion(station, motion)
                if t_start is not None:
                    while events and events[0].time <= self.clock.now() - t_start:
                        ev = events.pop(0)
                        station.grippers[ev.arm].command(ev.closed, ev.width, ev.force)
                if self.sim_time:  # joint states at state_rate up to the next frame time
                    t_next = self.clock.now() + 1.0 / fps
                    while next_state_t < t_next:
                        self.clock.sleep_until(next_state_t)
                        self._sample_states(station)
                        next_state_t += 1.0 / self.state_rate
                frame = self._read_frame(station)
                self._record_frame(frame, station)
                episode_frames += 1
                frames += 1
                self.summary.recorded_seconds += 1.0 / fps
                if t_start is not None:  # a fault shows in the episode holding the frame it happened in
                    for arm in station.arms.values():
                        arm.wait_motion(0.0)  # raises DeviceError on a fault
                self.progress.update(
                    f"[{item.index + 1}] {item.label} | episode {self._episode_index - 1} "
                    f"{episode_frames}/{per_episode} | recorded {self.summary.recorded_seconds:5.1f} s"
                    + (f"/{self._max_seconds:.0f} s" if self._max_seconds else "")
                    + f" | frames {self.summary.frames_captured} dropped {self.summary.frames_dropped}"
                )
                if self.stop_event.is_set():
                    break
            if chunk >= 0 and episode_frames:
                self._close_episode(station, episode_frames == per_episode)
            if t_start is not None and not self.stop_event.is_set():
                for arm in station.arms.values():
                    if not arm.wait_motion(timeout=max(1.0, motion.duration)):
                        raise DeviceError("arm did not finish its motion in time")
            else:
                for arm in station.arms.values():
                    arm.stop()
            return frames == total
        except DeviceError:
            self._close_episode(station, False, fault=True)
            resume.chunk = chunk + 1
            if t_start is not None:
                seg = int(motion.timed.segment_at(np.array([self.clock.now() - t_start]))[0])
                resume.waypoint = motion.waypoint_offset + motion.timed.segments[seg].to_waypoint
            raise
        finally:
            if poller:
                poller.__exit__(None, None, None)
                self.summary.errors.extend(poller.errors)

    def _start_motion(self, station: Station, motion: Any) -> float:
        """Start both arms together; returns the start time and logs the start skew."""
        t0 = self.clock.now()
        station.arms["left"].start_motion(motion.left)
        t1 = self.clock.now()
        station.arms["right"].start_motion(motion.right)
        skew = self.clock.now() - t0
        self.summary.start_skew_s = max(self.summary.start_skew_s, skew)
        log.debug("arm start skew %.3f ms (left call %.3f ms)", skew * 1e3, (t1 - t0) * 1e3)
        return t0

    def _record_frame(self, frame: RGBDFrame, station: Station) -> None:
        assert self._recorder is not None
        if self._last_frame_number is not None and frame.frame_number > self._last_frame_number + 1:
            self.summary.frames_dropped += frame.frame_number - self._last_frame_number - 1
        self._last_frame_number = frame.frame_number
        self.summary.frames_captured += 1
        self._recorder.frame(frame, station.T_world_cam)
        if self.bus is not None:
            self.bus.put(self._frame_key, encode_frame(frame, station.T_world_cam, station.camera.id, self._run_info))

    def _open_episode(self, meta: dict[str, Any]) -> None:
        assert self._recorder is not None
        free_gb = shutil.disk_usage(self.out_dir).free / 2**30
        if free_gb < self.config.output.min_free_gb:
            self.stop_event.set()
            self.summary.stopped_early = (
                f"only {free_gb:.1f} GiB free in {self.out_dir} (output.min_free_gb = {self.config.output.min_free_gb})"
            )
            return
        self._flush_pending(final=False)
        path = self.out_dir / f"episode_{self._episode_index:06d}.mcap"
        self._recorder.open_episode(path, {**meta, "episode_index": self._episode_index})
        self._item_episodes.append(path)
        self._episode_index += 1
        self._episode_open = True

    def _close_episode(self, station: Station, complete: bool, fault: bool = False) -> None:
        assert self._recorder is not None
        if not self._episode_open:
            return
        meta: dict[str, Any] = {"complete": complete, "fault": fault}  # every episode has both keys
        if station.sim is not None:
            meta.update(station.sim.episode_facts())
        self._recorder.close_episode(meta)
        self._episode_open = False

    def _base_metadata(self, item: RunItem, station: Station, motion: Any) -> dict[str, Any]:
        cam = station.camera.intrinsics
        return {
            "object": item.object.name,
            "category": item.object.category,
            "program": item.program,
            "speed": item.speed,
            "repeat": item.repeat,
            "run_index": item.index,
            "attempt": self._attempt,  # 1 + earlier starts of this run in this plan pass (journal)
            "plan_pass": self._pass,
            "session_started": self._session_started,  # UTC: tells a re-run's episodes from the cut-short ones
            "fps": station.fps,
            "episode_seconds": self.config.plan.episode_seconds,
            "segments": motion.segment_report,
            "calibration": {
                "width": cam.width, "height": cam.height, "K": cam.K.tolist(),
                "T_world_cam": station.T_world_cam.tolist(),
                "T_world_base": {n: station.bases[n].tolist() for n in ARMS},
                "depth_scale": 0.001,
            },
            "station": self.config.station.name,
            "clock": self.config.clock,
            "software": {"trackdeform3d": __version__},
            "arm_input_convention": (
                "u (12,) = [left TCP xyz m, left rotvec rad, right TCP xyz m, right rotvec rad], world frame"
            ),
        }
