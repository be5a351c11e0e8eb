"""The tracking worker: frames in over zenoh (ring channel, newest wins), live keypoints out.

It subscribes to ``<prefix>/<station>/cam/<id>/frame``, ``arms/state`` and the session's run
announcement ``session/run``, runs :class:`tracking.pipeline.LivePipeline` and publishes
``<prefix>/<station>/keypoints`` (JSON, see ``tdcommon.wire.encode_keypoints``) stamped with the
announced session and run ids. It starts a new tracker only when the session announces another track
(``track_id``, default the run id; never on a frame's own header): the session's live initialisation
(``orchestrator.liveinit``) announces its frames as a run of their own with the track id the object's
recorded runs then carry, so the tracker initialised on them goes on into the recording. A frame whose
header names another run than the announced one makes the worker ask the session (``session/run``,
a get) once, in case that announcement is still on its way. It declares the liveliness token
``worker/alive/<host>-<pid>`` once it is ready, and, started by a session, dies with it
(``PR_SET_PDEATHSIG`` and a parent-pid check).
Run it as ``trackdeform worker CONFIG`` or ``python -m orchestrator.worker CONFIG``.
"""

from __future__ import annotations

import argparse
import ctypes
import logging
import os
import re
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tdcommon.meshes import merge_meshes
from tdcommon.objects import DIMENSION, default_keypoints
from tracking.params import TrackingParams
from tracking.pipeline import LivePipeline, PipelineOutput

log = logging.getLogger("trackdeform.worker")
PENDING_S = 5.0  # s a frame of a not yet announced run is retried before it is dropped


def tracking_params(tracking: Any, category: str | None = None, n_keypoints: int | None = None) -> TrackingParams:
    """TrackingParams from the config's ``tracking`` section and the object (category, keypoint count)."""
    p = TrackingParams()
    p = replace(
        p,
        voxel_m=tracking.voxel_size,
        track_iterations=tracking.solver_iterations,
        use_anchors=tracking.use_anchors,
        use_edge_projection=tracking.use_edge_projection,
        use_cloud_projection=tracking.use_cloud_projection,
        causal_window=tracking.live_window,
        symmetric_window=tracking.final_window,
    )
    if category in ("dlo", "bdlo"):
        p = replace(p, n_keypoints_1d=n_keypoints or default_keypoints(category))
    elif category == "cloth" and n_keypoints:
        side = max(2, int(round(np.sqrt(n_keypoints))))
        p = replace(p, grid_rows=side, grid_cols=side)
    return p


class ArmModel:
    """Both arms' meshes and TCPs from a joint-state message (``arms/state`` JSON)."""

    def __init__(self, bases: dict[str, np.ndarray]) -> None:
        from tdcommon.robot import PandaKinematics

        self.kin = {n: PandaKinematics(bases[n]) for n in ("left", "right")}

    def from_state(
        self, state: dict[str, Any]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """vertices (V, 3), triangles (F, 3), tcp (2, 3) m world, closed (2,) bool, tcp_rot (2, 3, 3) (TCP frame
        to world)."""
        meshes, poses, closed = [], [], []
        for n in ("left", "right"):
            q = np.asarray(state[n]["q"], np.float64)
            meshes.append(self.kin[n].world_meshes(q, float(state[n].get("gripper_width", 0.08))))
            poses.append(self.kin[n].tcp_pose(q))
            closed.append(bool(state[n].get("grasped", False)))
        verts, tris = merge_meshes(meshes)
        T = np.stack(poses)
        return verts, tris, T[:, :3, 3].copy(), np.asarray(closed), T[:, :3, :3].copy()


@dataclass
class WorkerStats:
    """Counters the worker logs and returns."""

    frames: int = 0
    skipped: int = 0
    published: int = 0
    initialisations: int = 0
    lost: int = 0
    busy_s: float = 0.0
    no_run: int = 0  # frames dropped because no run was announced (yet)
    other_run: int = 0  # frames whose header names another run than the announced one
    runs: int = 0  # trackers started (one per announced track)


def keypoint_message(out: PipelineOutput, frame_number: int, stamp: float, run: dict[str, Any], ms: float) -> bytes:
    """The ``keypoints`` message of one processed frame; ``run`` is the session's run announcement."""
    from tdcommon.wire import encode_keypoints

    topo = out.topology
    edges = topo.edges if topo is not None and len(out.keypoints) else np.zeros((0, 2), np.int64)
    grasp = {n: int(out.grasp_idx[i]) if i < len(out.grasp_idx) else -1 for i, n in enumerate(("left", "right"))}
    return encode_keypoints(
        frame_number=frame_number, stamp=stamp, keypoints=out.keypoints, edges=edges, grasp_indices=grasp,
        object_name=str(run.get("object", "")), category=str(run.get("category", "")), status=out.status,
        abs_mm=None if np.isnan(out.abs_mm) else out.abs_mm, cd_mm=None if np.isnan(out.cd_mm) else out.cd_mm,
        anchors=topo.anchor_idx if topo is not None and len(out.keypoints) else None,
        extra={
            "smoothed": np.round(out.smoothed, 6).tolist(),
            "rest_lengths": (np.round(topo.reference_lengths, 6).tolist()
                             if topo is not None and len(out.keypoints) else []),
            "n_points": out.n_points, "processing_ms": round(ms, 2), "note": out.note,
            "run_index": run.get("run_index"),
        },
        session_id=str(run.get("session_id", "")), run_id=str(run.get("run_id", "")),
    )


def worker_id() -> str:
    """``<host>-<pid>``, usable in a zenoh key."""
    return f"{re.sub(r'[^A-Za-z0-9_-]', '_', socket.gethostname())}-{os.getpid()}"


def die_with_parent(parent_pid: int) -> bool:
    """Ask Linux to SIGKILL this process when its parent dies (``PR_SET_PDEATHSIG``); False when not possible.

    Raises SystemExit when the parent is already gone (it died before the request was made).
    """
    ok = False
    if sys.platform.startswith("linux"):
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            ok = libc.prctl(1, int(signal.SIGKILL), 0, 0, 0) == 0  # 1 = PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            ok = False
    if os.getppid() != parent_pid:
        raise SystemExit(f"worker: parent {parent_pid} is gone")
    return ok


class Worker:
    """Subscribes, tracks, publishes; ``run`` until ``stop`` is set."""

    def __init__(self, config: Any, connect: list[str] | None = None, session_id: str | None = None,
                 parent_pid: int | None = None) -> None:
        from orchestrator.bus import Bus, local_endpoints
        from orchestrator.live import KindCounter

        self.config = config
        endpoints = connect or config.bus.connect or local_endpoints(config.bus.listen)
        self.bus = Bus(config.bus, config.station.name, listen=False, connect=endpoints)
        st = config.station
        self.arms = ArmModel({"left": st.left.arm.base.matrix(), "right": st.right.arm.base.matrix()})
        self._state: dict[str, Any] | None = None
        self._lock = threading.Lock()
        self.frame_sub = self.bus.subscribe(self.bus.key("cam", st.camera.id, "frame"), ring=1)
        self.bus.subscribe(self.bus.key("arms", "state"), callback=self._on_state)
        self.key_out = self.bus.key("keypoints")
        self.session_id = session_id  # None: follow whichever session announces a run
        self.parent_pid = parent_pid
        self.malformed = KindCounter("frame not tracked", log)
        self.pipeline: LivePipeline | None = None
        self._track_id: str | None = None  # the track the pipeline follows (announced track_id, else run_id)
        self._asked: tuple[str, float] = ("", -1e9)  # the header run id last asked about, monotonic s
        self._reference_gap: int | None = None  # the pipeline's own, while a P0 / P1 initialisation overrides it
        self._announced: dict[str, Any] | None = None  # the newest run announcement of our session
        self._last_frame: int | None = None
        # the newest frame naming a run not (yet) announced, kept for PENDING_S: its announcement may trail it,
        # and in simulated time no newer frame comes until that frame is answered
        self._pending: tuple[Any, float] | None = None
        self._past_runs: set[str] = set()  # run ids announced before: their late frames are not pending
        self.stats = WorkerStats()
        self._run_key = self.bus.key("session", "run")
        self.bus.subscribe(self._run_key, callback=self._on_run)
        self._query_announcement(2.0)  # the run under way (a restarted worker does not wait for the next one)
        self.id = worker_id()
        self.bus.declare_token(self.bus.key("worker", "alive", self.id))  # ready: the supervisor sees us up

    def _query_announcement(self, timeout: float) -> None:
        """Ask the session for its current run announcement (``session/run`` get) and follow it."""
        try:
            for payload in self.bus.get(self._run_key, timeout=timeout):
                self._take_announcement(payload)
        except Exception as e:  # no session yet: its announcement comes by the subscriber
            log.debug("no run announcement to query: %s", e)

    def _on_run(self, sample: Any) -> None:
        self._take_announcement(sample.payload.to_bytes())

    def _take_announcement(self, payload: bytes) -> None:
        """Follow a ``session/run`` announcement of our session (any session when started without one)."""
        from tdcommon.wire import decode_json

        try:
            msg = decode_json(payload)
            sid, rid = str(msg["session_id"]), str(msg["run_id"])
        except (ValueError, KeyError, TypeError) as e:
            self.malformed.add("announcement", f"not a run announcement: {e}")
            return
        if self.session_id is not None and sid != self.session_id:
            self.malformed.add("other_session", f"announcement of session {sid!r}, following {self.session_id!r}")
            return
        with self._lock:
            if self._announced is not None:
                self._past_runs.add(str(self._announced.get("run_id", "")))
            self._announced = msg if rid else None

    def _on_state(self, sample: Any) -> None:
        from tdcommon.wire import decode_json

        try:
            msg = decode_json(sample.payload.to_bytes())
        except ValueError:
            return
        with self._lock:
            self._state = msg

    def _pipeline_for(self, run: dict[str, Any], K: np.ndarray, T: np.ndarray) -> LivePipeline:
        """The tracker of the announced ``run``: a new one only when the announced track changes
        (``track_id``, else the run id): a run announced with the track of the live initialisation before it
        keeps that initialisation (warm start)."""
        track = str(run.get("track_id") or run["run_id"])
        if self.pipeline is None or track != self._track_id:
            category = run.get("category")
            params = tracking_params(self.config.tracking, category, run.get("n_keypoints"))
            self.pipeline = LivePipeline(params, K, T, DIMENSION.get(category))
            if run.get("phase") == "init":
                # the session's P0 / P1 initialisation: P1 (the arms holding still at the second configuration)
                # is differenced against the reference P0 alone; recent frames become references again once
                # it is initialised (see step), for a re-initialisation after a lost track
                self._reference_gap = self.pipeline.reference_gap
                self.pipeline.reference_gap = 1 << 30
            self._track_id = track
            self.stats.runs += 1
            log.info("new track %s for %s run %s (%s): tracking %s (%s)", track, run.get("phase", "record"),
                     run.get("run_index"), run["run_id"], run.get("object"), category)
        return self.pipeline

    def _announcement_for(self, header_run: str) -> dict[str, Any] | None:
        """The announced run, after asking the session once when a frame's header names another run (its
        announcement may trail the frame); at most one question every 0.5 s."""
        with self._lock:
            run = self._announced
        if not header_run or (run is not None and header_run == run["run_id"]):
            return run
        asked, when = self._asked
        now = time.monotonic()
        if now - when >= 0.5 and (header_run != asked or self._pending is not None):
            self._asked = (header_run, now)
            self._query_announcement(0.5)
            with self._lock:
                run = self._announced
        return run

    def step(self) -> bool:
        """Process the newest frame if there is one; False when none was waiting (a pending frame of a run not
        yet announced is retried then, for up to PENDING_S)."""
        sample = self.frame_sub.try_recv()
        if sample is not None:
            self._pending = None
            self._handle(sample, time.monotonic(), retry=False)
            return True
        if self._pending is not None:
            sample, since = self._pending
            self._pending = None
            if time.monotonic() - since <= PENDING_S:
                time.sleep(0.05)
                self._handle(sample, since, retry=True)
        return False

    def _handle(self, sample: Any, since: float, retry: bool) -> None:  # noqa: ANN401 - a zenoh sample
        """Track one received frame (``since``: when it first came; ``retry``: it waited for its run)."""
        from tdcommon.wire import decode_frame

        t0 = time.perf_counter()
        try:
            msg = decode_frame(sample.payload.to_bytes())
        except (ValueError, KeyError, TypeError) as e:
            self.malformed.add("frame", f"{type(e).__name__}: {e}")
            return
        frame = msg.frame
        if retry:
            self._last_frame = frame.frame_number - 1  # counted once, when it first came
        if self._last_frame is not None and frame.frame_number > self._last_frame + 1:
            self.stats.skipped += frame.frame_number - self._last_frame - 1  # ring channel: newest wins
        self._last_frame = frame.frame_number
        run = self._announcement_for(str(msg.run.get("run_id", "")))
        with self._lock:
            state = msg.joint_state or self._state  # the arms at the frame's capture time, when paired
        if run is None:
            self.stats.no_run += not retry
            if msg.run.get("run_id") and str(msg.run.get("run_id")) not in self._past_runs:
                self._pending = (sample, since)  # its announcement may trail it
            return
        if msg.run.get("run_id", run["run_id"]) != run["run_id"]:  # a frame of another run: not ours to track
            self.stats.other_run += not retry  # counted when it came (it may still be tracked, below)
            if str(msg.run.get("run_id")) not in self._past_runs:  # perhaps the next run, announced late
                self._pending = (sample, since)
                return  # the announced run decides; at a run change one old frame may be waiting
            log.debug("frame %d of run %r skipped (tracking %r)", frame.frame_number, msg.run.get("run_id"),
                      run["run_id"])
            return
        pipe = self._pipeline_for(run, frame.intrinsics.K, msg.T_world_cam)
        if run.get("phase") == "init" and msg.run.get("init_step") == "move" and pipe.state == "waiting":
            # on the way from P0 to P1 the object is still moving: the initialisation waits for P1
            out = PipelineOutput("waiting", np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64),
                                 float("nan"), float("nan"), 0, note="moving to the second configuration P1")
            ms = (time.perf_counter() - t0) * 1e3
            self.bus.put(self.key_out, keypoint_message(out, frame.frame_number, frame.device_stamp, run, ms))
            self.stats.frames += 1
            self.stats.published += 1
            return
        V = F = tcp = closed = rot = None
        if state is not None:
            V, F, tcp, closed, rot = self.arms.from_state(state)
        before = pipe.state
        out = pipe.process(frame.depth_m(), V, F, tcp, closed, tcp_rot=rot, colour=frame.color)
        if self._reference_gap is not None and pipe.state == "tracking":
            pipe.reference_gap, self._reference_gap = self._reference_gap, None
        if out.status == "init":
            self.stats.initialisations += 1
        if out.status == "lost":
            self.stats.lost += 1
        ms = (time.perf_counter() - t0) * 1e3
        self.bus.put(self.key_out, keypoint_message(out, frame.frame_number, frame.device_stamp, run, ms))
        self.stats.frames += 1
        self.stats.published += 1
        self.stats.busy_s += ms / 1e3
        if before != pipe.state:
            log.info("frame %d: %s -> %s %s", frame.frame_number, before, pipe.state, out.note)

    def run(self, stop: threading.Event, max_frames: int | None = None) -> WorkerStats:
        """Poll with ``try_recv`` (a thread blocked in ``recv`` would make undeclare abort) until stopped."""
        last_log = last_parent = time.monotonic()
        while not stop.is_set() and (max_frames is None or self.stats.frames < max_frames):
            try:
                busy = self.step()
            except Exception as e:  # one bad frame must not end the worker; logged once per kind
                self.malformed.add(f"tracking {type(e).__name__}", str(e))
                busy = True
            if not busy:
                time.sleep(0.002)
            if self.parent_pid is not None and time.monotonic() - last_parent > 0.5:
                last_parent = time.monotonic()
                if os.getppid() != self.parent_pid:
                    log.warning("the session (pid %d) is gone: stopping", self.parent_pid)
                    break
            if time.monotonic() - last_log > 5.0:
                last_log = time.monotonic()
                s = self.stats
                log.info("frames %d, init %d, lost %d, mean %.1f ms", s.frames, s.initialisations, s.lost,
                         1e3 * s.busy_s / max(1, s.frames))
        return self.stats

    def close(self) -> None:
        """Undeclare and close the zenoh session."""
        self.bus.close()


def main(argv: list[str] | None = None) -> int:
    """``python -m orchestrator.worker CONFIG [--connect ENDPOINT ...]``."""
    from orchestrator.config import ConfigError, load_config

    ap = argparse.ArgumentParser(prog="trackdeform worker", description=__doc__.splitlines()[0])
    ap.add_argument("config", help="station config (YAML or JSON)")
    ap.add_argument("--connect", action="append", help="zenoh endpoint of the daemon or router (repeatable)")
    ap.add_argument("--max-frames", type=int, help="stop after this many frames")
    ap.add_argument("--session-id", help="follow only this session's run announcements (set by the session)")
    ap.add_argument("--parent-pid", type=int, help="exit when this process (the session) dies")
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        config = load_config(args.config)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.parent_pid is not None and not die_with_parent(args.parent_pid):
        log.warning("PR_SET_PDEATHSIG unavailable: relying on the parent-pid check")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    worker = Worker(config, args.connect, session_id=args.session_id, parent_pid=args.parent_pid)
    try:
        stats = worker.run(stop, args.max_frames)
    finally:
        worker.close()
    print(f"worker: {stats.frames} frames ({stats.skipped} skipped, {stats.no_run} before a run announcement, "
          f"{worker.malformed.total()} malformed), {stats.runs} runs, {stats.initialisations} initialisations, "
          f"{stats.lost} lost, mean {1e3 * stats.busy_s / max(1, stats.frames):.1f} ms/frame", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
