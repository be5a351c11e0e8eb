"""One program run's capture: frames cut into whole episodes, gripper events on time, faults resumed.

:class:`EpisodeStream` owns a session's episode files (numbering, the disk-space guard, open / close)
and sends every frame and joint state to the recorder and the bus. :class:`RunCapture` records one run
item on a connected station through it: one loop driven by the camera, joint states sampled between
frames (a thread in real time, inline in simulated time), and after a recoverable arm fault a retry of
the faulted segment from where the arms are.
"""

from __future__ import annotations

import logging
import math
import threading
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import DeviceError
from drivers.clock import Clock
from orchestrator import __version__
from orchestrator.bus import Bus
from orchestrator.config import Config, SyncConfig
from orchestrator.fsutil import free_bytes
from orchestrator.health import SessionMonitor
from orchestrator.live import KeypointGate
from orchestrator.plan import RunItem
from orchestrator.programs import PlannedMotion, ProgramRejected, plan_motion
from orchestrator.progress import Progress
from orchestrator.recorder import Recorder, RecordingFailed
from orchestrator.station import ARMS, StatePoller, Station
from orchestrator.summary import SessionSummary
from orchestrator.timesync import TimeSync
from tdcommon.transforms import pose_to_input
from tdcommon.types import RGBDFrame
from tdcommon.wire import encode_frame, encode_json

log = logging.getLogger(__name__)
SIM_FIRST_FRAME_WAIT_S = 10.0  # simulated time, live-initialised run: wall s an episode's first frame waits at most


class LowDisk(RuntimeError):
    """Free space fell below ``output.min_free_gb``: no episode opens, the open one closes incomplete."""


class EpisodeStream:
    """A session's episode files and live streams: every frame and joint state goes to the recorder and,
    when there is one, the bus; episodes are numbered on from those already in the folder.

    Free space is checked before each episode opens and every ``disk_check_seconds`` of frames
    during one: below ``min_free_gb`` :class:`LowDisk` is raised. Once the recorder has failed
    (an I/O error) :class:`RecordingFailed` is raised instead of recording or opening anything.

    Every frame is paired with both arms' joint states at its capture time (:mod:`orchestrator.timesync`):
    the pair is recorded (``/arms/state_at_frame``), sent with the frame on the bus (``joint_state``: the
    worker's arm mask uses it) and each episode's metadata gets the sync figures (``time_sync``).
    """

    def __init__(self, out_dir: Path, recorder: Recorder, bus: Bus | None, camera_id: str, summary: SessionSummary,
                 *, min_free_gb: float, stop_event: threading.Event, before_open: Callable[[], None],
                 disk_check_seconds: float = 1.0, sync: SyncConfig | None = None) -> None:
        self.out_dir = out_dir
        self.recorder = recorder
        self.bus = bus
        self.summary = summary
        self.min_free_gb = min_free_gb
        self.disk_check_seconds = disk_check_seconds
        sc = sync or SyncConfig()
        self.sync = TimeSync(sc.camera_latency_s, self._tcp_input, sc.offset_window_s, sc.max_pairing_gap_s)
        self._station: Station | None = None
        self._last_device_stamp: float | None = None
        self._frames_since_check = 0
        self.stop_event = stop_event
        self.before_open = before_open  # called before each new file (the journal catches up on done runs)
        self.next_index = next_episode_index(out_dir)
        self.episode_open = False
        self.last_frame_number: int | None = None
        self.run_info: dict[str, Any] = {}  # what is being recorded, sent with every frame on the bus
        self.gate: KeypointGate | None = None  # checks live keypoints and counts tracking gaps (with a bus)
        self.monitor: SessionMonitor | None = None  # announces runs; health
        self._frame_key = bus.key("cam", camera_id, "frame") if bus is not None else ""
        self._state_key = bus.key("arms", "state") if bus is not None else ""

    def disk_low(self) -> str | None:
        """Why the disk is too full to record (free space below ``min_free_gb``), or None."""
        free_gb = free_bytes(self.out_dir) / 2**30
        if free_gb < self.min_free_gb:
            return f"only {free_gb:.2f} GiB free in {self.out_dir} (output.min_free_gb = {self.min_free_gb})"
        return None

    def check_recorder(self) -> None:
        """Raise RecordingFailed once the recorder has stopped on an I/O error."""
        if self.recorder.failed is not None:
            raise RecordingFailed(self.recorder.failed)

    def open_episode(self, meta: dict[str, Any]) -> Path:
        """Open the next episode file; LowDisk below ``min_free_gb``, RecordingFailed after an I/O error."""
        self.check_recorder()
        low = self.disk_low()
        if low is not None:
            raise LowDisk(low)
        self._frames_since_check = 0
        self.sync.reset_episode()
        self.before_open()
        path = self.out_dir / f"episode_{self.next_index:06d}.mcap"
        self.recorder.open_episode(path, {**meta, "episode_index": self.next_index})
        self.next_index += 1
        self.episode_open = True
        return path

    def close_episode(self, station: Station, complete: bool, fault: bool = False) -> None:
        """Close the open episode (if any) with its ``complete`` / ``fault`` flags and the simulator's facts."""
        if not self.episode_open:
            return
        meta: dict[str, Any] = {"complete": complete, "fault": fault}  # every episode has both keys
        meta["time_sync"] = self.sync.episode_report(self._last_device_stamp)
        if station.sim is not None:
            meta.update(station.sim.episode_facts())
        if self.gate is not None:  # keypoints received by now; the worker runs a few frames behind
            meta["tracking"] = report = self.gate.episode_report()
            self.summary.tracking_gaps += report["gaps"]
            self.summary.tracking_gap_frames += report["gap_frames"]
        self.recorder.close_episode(meta)
        self.episode_open = False

    def record_frame(self, frame: RGBDFrame, station: Station) -> None:
        """Count (and count drops by frame number), record and publish one frame."""
        if self.last_frame_number is not None and frame.frame_number > self.last_frame_number + 1:
            self.summary.frames_dropped += frame.frame_number - self.last_frame_number - 1
        self.last_frame_number = frame.frame_number
        self.summary.frames_captured += 1
        self.check_recorder()
        self._station = station
        self._last_device_stamp = frame.device_stamp
        paired = self.sync.pair(frame.frame_number, frame.device_stamp, frame.host_stamp)
        self.recorder.frame(frame, station.T_world_cam, paired)
        if self.gate is not None:
            self.gate.frame(frame.frame_number, frame.device_stamp)
        if self.bus is not None:
            self.bus.put(self._frame_key, encode_frame(frame, station.T_world_cam, station.camera.id, self.run_info,
                                                       joint_state=paired))
        self._frames_since_check += 1
        if self.episode_open and self._frames_since_check >= max(1, round(self.disk_check_seconds * station.fps)):
            self._frames_since_check = 0
            low = self.disk_low()
            if low is not None:
                raise LowDisk(low)

    def publish_frame(self, frame: RGBDFrame, station: Station) -> None:
        """Publish one frame on the bus, paired with the joints at its capture time, without recording or
        counting it (the live initialisation's frames: ``orchestrator.liveinit``)."""
        self._station = station
        paired = self.sync.pair(frame.frame_number, frame.device_stamp, frame.host_stamp)
        if self.bus is not None:
            self.bus.put(self._frame_key, encode_frame(frame, station.T_world_cam, station.camera.id, self.run_info,
                                                       joint_state=paired))

    def publish_states(self, station: Station) -> None:
        """Sample both arms once and publish ``arms/state`` (for pairing too) without recording the sample."""
        msg, _ = station.sample_state()
        self.sync.states.add(msg)
        if self.bus is not None:
            self.bus.put(self._state_key, encode_json(msg))

    def begin_init(self, run_id: str, info: dict[str, Any], label: str) -> None:
        """Frames from now on are the live initialisation's ``run_id`` (published, not recorded): announced on the
        bus like a run (the tracker follows it); the gate records nothing meanwhile."""
        self.run_info = {**info, "run_id": run_id}
        if self.gate is not None:
            self.gate.begin_run("")
        if self.monitor is not None:
            self.monitor.announce_run(run_id, info, label)

    def begin_run(self, run_id: str, info: dict[str, Any], label: str) -> None:
        """Frames from now on belong to run ``run_id``: announced on the bus (the tracker follows it)."""
        self.run_info = {**info, "run_id": run_id}
        if self.gate is not None:
            self.gate.begin_run(run_id)
        if self.monitor is not None:
            self.monitor.announce_run(run_id, info, label)

    def sample_states(self, station: Station) -> None:
        """Sample both arms once; record and publish the ``arms/state`` message."""
        msg, tcps = station.sample_state()
        self.sync.states.add(msg)
        self.summary.state_samples += 1
        self.recorder.arm_state(msg, tcps)
        if self.bus is not None:
            self.bus.put(self._state_key, encode_json(msg))


    def _tcp_input(self, arm: str, q: np.ndarray) -> np.ndarray:
        """u of one arm (6,): TCP position m + rotation vector rad, world frame, for joints q (7,)."""
        assert self._station is not None
        return pose_to_input(self._station.kin[arm].tcp_pose(q))


def next_episode_index(out_dir: Path) -> int:
    """Continue numbering after the episodes already in the folder or its quarantine (a resumed session)."""
    idx = []
    for p in [*out_dir.glob("episode_*.mcap*"), *out_dir.glob("quarantine/episode_*.mcap*")]:
        number = p.name.split("_")[1].split(".")[0]
        if number.isdigit():
            idx.append(int(number))
    return max(idx) + 1 if idx else 0


class RunPaused(Exception):
    """``ctl pause`` at an episode boundary: the arms stop, the run continues from its waypoint on resume."""


class RunSkipped(Exception):
    """``ctl skip``: the run ends now, journaled as skipped."""


@dataclass
class Resume:
    """Where a program run continues after a recovered fault: a waypoint and the next chunk index."""

    waypoint: int = 0
    chunk: int = 0


@dataclass(frozen=True)
class RunContext:
    """What one run is recorded within: the session's clock, config, streams and stop conditions.

    ``run_meta`` goes into every episode's metadata (attempt, plan_pass, session_started, live_init);
    ``announce`` into the run's announcement (``track_id``: the live initialisation's track the worker keeps).
    """

    config: Config
    clock: Clock
    stream: EpisodeStream
    summary: SessionSummary
    progress: Progress
    stop_event: threading.Event
    should_stop: Callable[[], bool]
    max_seconds: float | None
    state_rate: float
    run_meta: dict[str, Any]
    control: SessionMonitor | None = None  # pause / skip requests, state, where the run is
    announce: dict[str, Any] = field(default_factory=dict)  # extra run-announcement fields (track_id)


class RunCapture:
    """Records one run item on a connected station as whole episodes: ``RunCapture(ctx, item, station).run()``."""

    def __init__(self, ctx: RunContext, item: RunItem, station: Station) -> None:
        self.ctx = ctx
        self.item = item
        self.station = station
        self.episodes: list[Path] = []  # the files this run opened, in order
        self.run_id = uuid.uuid4().hex[:12]  # in the run announcement and every keypoint message of this run

    def run(self, retries: int = 2) -> tuple[str, str | None]:
        """Record the run; after a recoverable fault, recover and retry the faulted segment at slow speed.

        Returns ("done" | "stopped" | "skipped" | "failed" | "low_disk", the failure or skip message or None).
        A recorder that failed (an I/O error) fails the run; low disk space closes the open episode
        (``complete: false``) and ends the run as "low_disk" (the session stops or pauses).
        """
        ctx, item, station = self.ctx, self.item, self.station
        resume = Resume()
        attempt = 0
        while True:
            try:
                complete = self._record(resume)
                ctx.summary.runs_done += 1
                return ("done", None) if complete else ("stopped", None)
            except RunSkipped:
                station.stop_arms()
                ctx.summary.runs_skipped.append(item.label)
                return "skipped", "skipped by `trackdeform ctl skip`"
            except RunPaused:
                station.stop_arms()
                assert ctx.control is not None
                ctx.control.hold()
                if ctx.stop_event.is_set():
                    return "stopped", None
                if ctx.control.take_skip():
                    ctx.summary.runs_skipped.append(item.label)
                    return "skipped", "skipped by `trackdeform ctl skip` while paused"
                ctx.progress.message(f"resumed; continuing from waypoint {resume.waypoint} (approach at slow speed)")
            except DeviceError as e:
                msg = f"{item.label}: device fault: {e}"
                log.warning(msg)
                ctx.progress.message(f"warning: {msg}")
                station.stop_arms()
                if not e.recoverable or attempt == retries:
                    ctx.summary.runs_failed.append(msg)
                    if not e.recoverable:
                        station.broken = str(e)
                    return "failed", msg
                if ctx.control is not None:
                    ctx.control.set_state("recovering", msg)
                try:
                    station.recover()
                except DeviceError as e2:
                    ctx.summary.runs_failed.append(f"{msg}; recovery failed: {e2}")
                    station.broken = f"recovery failed: {e2}"
                    return "failed", f"{msg}; recovery failed: {e2}"
                ctx.summary.faults_recovered += 1
                if ctx.control is not None:
                    ctx.control.incident("device_fault", f"{msg}; recovered")
                    ctx.control.set_state("running")
                ctx.progress.message(f"recovered; retrying from waypoint {resume.waypoint} (approach at slow speed)")
                attempt += 1
            except ProgramRejected as e:
                ctx.summary.runs_failed.append(f"{item.label}: {e}")
                ctx.progress.message(f"error: {item.label}: {e}")
                return "failed", f"{item.label}: {e}"
            except LowDisk as e:
                station.stop_arms()
                ctx.stream.close_episode(station, False)
                return "low_disk", f"{item.label}: {e}"
            except RecordingFailed as e:
                station.stop_arms()
                ctx.stream.episode_open = False  # the recorder takes no close any more
                msg = f"{item.label}: recording failed: {e}"
                ctx.summary.runs_failed.append(msg)
                return "failed", msg

    def _record(self, resume: Resume) -> bool:
        """Record the run (from ``resume.waypoint`` after a fault) as whole episodes.

        Returns False when a stop (signal, ``max_seconds``, low disk) cut the run short.
        On a DeviceError, ``resume`` is updated with the waypoint to retry from and the next chunk index.
        """
        ctx, item, station, stream = self.ctx, self.item, self.station, self.ctx.stream
        clock, plan = ctx.clock, ctx.config.plan
        sim_time = ctx.config.clock == "sim"
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
        base_meta = self._base_metadata(motion)
        base_meta["start_waypoint"] = resume.waypoint
        stream.last_frame_number = None  # frames the camera made between runs were not meant to be recorded
        stream.begin_run(self.run_id, {
            "object": item.object.name, "category": item.object.category, "program": item.program,
            "speed": item.speed, "run_index": item.index, "n_keypoints": item.object.n_keypoints, "phase": "record",
            **ctx.announce,
        }, item.label)
        control = ctx.control
        poller = None if sim_time else StatePoller(lambda: stream.sample_states(station), ctx.state_rate)
        next_state_t = clock.now()
        try:
            if poller:
                poller.__enter__()
            for k in range(total):
                if control is not None:
                    control.at_frame(k, total, stream.next_index - 1)
                    if control.take_skip():
                        raise RunSkipped
                if k % per_episode == 0:
                    if chunk >= 0:
                        stream.close_episode(station, episode_frames == per_episode)
                    if ctx.should_stop():
                        break
                    if k > 0 and control is not None and control.pause_requested():
                        raise RunPaused
                    chunk += 1
                    episode_frames = 0
                    self.episodes.append(stream.open_episode({**base_meta, "chunk_index": chunk}))
                if k == settle_frames:
                    t_start = self._start_motion(motion)
                if t_start is not None:
                    while events and events[0].time <= clock.now() - t_start:
                        ev = events.pop(0)
                        station.grippers[ev.arm].command(ev.closed, ev.width, ev.force)
                if sim_time:  # joint states at state_rate up to the next frame time
                    t_next = clock.now() + 1.0 / fps
                    while next_state_t < t_next:
                        clock.sleep_until(next_state_t)
                        stream.sample_states(station)
                        next_state_t += 1.0 / ctx.state_rate
                frame = station.read_frame()
                stream.record_frame(frame, station)
                if sim_time and episode_frames == 0 and stream.gate is not None and ctx.announce.get("track_id"):
                    # the camera does not pace simulated time: let the (initialised) worker have each episode's
                    # first frame before the next one replaces it on the ring channel
                    stream.gate.wait_keypoints(frame.frame_number, SIM_FIRST_FRAME_WAIT_S)
                episode_frames += 1
                frames += 1
                ctx.summary.recorded_seconds += 1.0 / fps
                if t_start is not None:  # a fault shows in the episode holding the frame it happened in
                    for arm in station.arms.values():
                        arm.wait_motion(0.0)  # raises DeviceError on a fault
                ctx.progress.update(
                    f"[{item.index + 1}] {item.label} | episode {stream.next_index - 1} "
                    f"{episode_frames}/{per_episode} | recorded {ctx.summary.recorded_seconds:5.1f} s"
                    + (f"/{ctx.max_seconds:.0f} s" if ctx.max_seconds else "")
                    + f" | frames {ctx.summary.frames_captured} dropped {ctx.summary.frames_dropped}"
                )
                if ctx.stop_event.is_set():
                    break
            if chunk >= 0 and episode_frames:
                stream.close_episode(station, episode_frames == per_episode)
            if t_start is not None and not ctx.stop_event.is_set():
                for arm in station.arms.values():
                    if not arm.wait_motion(timeout=max(1.0, motion.duration)):
                        raise DeviceError("arm did not finish its motion in time")
            else:
                for arm in station.arms.values():
                    arm.stop()
            return frames == total
        except RunSkipped:
            stream.close_episode(station, False)
            raise
        except (DeviceError, RunPaused) as e:
            stream.close_episode(station, False, fault=isinstance(e, DeviceError))  # a pause closed it already
            resume.chunk = chunk + 1
            if t_start is not None:
                seg = int(motion.timed.segment_at(np.array([clock.now() - t_start]))[0])
                resume.waypoint = motion.waypoint_offset + motion.timed.segments[seg].to_waypoint
            raise
        finally:
            if poller:
                poller.__exit__(None, None, None)
                ctx.summary.errors.extend(poller.errors)

    def _start_motion(self, motion: PlannedMotion) -> float:
        """Start both arms together; returns the start time and keeps the largest start skew."""
        clock, arms = self.ctx.clock, self.station.arms
        t0 = clock.now()
        arms["left"].start_motion(motion.left)
        t1 = clock.now()
        arms["right"].start_motion(motion.right)
        skew = clock.now() - t0
        self.ctx.summary.start_skew_s = max(self.ctx.summary.start_skew_s, skew)
        log.debug("arm start skew %.3f ms (left call %.3f ms)", skew * 1e3, (t1 - t0) * 1e3)
        return t0

    def _base_metadata(self, motion: PlannedMotion) -> dict[str, Any]:
        """The metadata every episode of this run opens with."""
        item, station, config = self.item, self.station, self.ctx.config
        cam = station.camera.intrinsics
        return {
            "object": item.object.name,
            "category": item.object.category,
            "program": item.program,
            "speed": item.speed,
            "repeat": item.repeat,
            "run_index": item.index,
            **self.ctx.run_meta,
            "fps": station.fps,
            "episode_seconds": config.plan.episode_seconds,
            "segments": motion.segment_report,
            "calibration": {
                "width": cam.width, "height": cam.height, "K": cam.K.tolist(),
                "T_world_cam": station.T_world_cam.tolist(),
                "T_world_base": {n: station.bases[n].tolist() for n in ARMS},
                "depth_scale": 0.001,
            },
            "station": config.station.name,
            "clock": config.clock,
            "software": {"trackdeform3d": __version__},
            "arm_input_convention": (
                "u (12,) = [left TCP xyz m, left rotvec rad, right TCP xyz m, right rotvec rad], world frame"
            ),
        }
