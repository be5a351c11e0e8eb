"""The tracking worker: frames in over zenoh (ring channel, newest wins), live keypoints out.

The only module of ``tracking/`` that touches zenoh and the configuration: it subscribes to
``<prefix>/<station>/cam/<id>/frame`` and ``arms/state``, runs :class:`tracking.pipeline.LivePipeline`
and publishes ``<prefix>/<station>/keypoints`` (JSON, see ``tdcommon.wire.encode_keypoints``).
Run it as ``trackdeform worker CONFIG`` or ``python -m orchestrator.worker CONFIG``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from orchestrator.ratelog import OncePerKind
from tdcommon.meshes import merge_meshes
from tdcommon.objects import DIMENSION, default_keypoints
from tracking.params import TrackingParams
from tracking.pipeline import LivePipeline, PipelineOutput

log = logging.getLogger("trackdeform.worker")


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

    def from_state(self, state: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """vertices (V, 3), triangles (F, 3), tcp (2, 3) m world, closed (2,) bool."""
        meshes, tcp, closed = [], [], []
        for n in ("left", "right"):
            q = np.asarray(state[n]["q"], np.float64)
            meshes.append(self.kin[n].world_meshes(q, float(state[n].get("gripper_width", 0.08))))
            tcp.append(self.kin[n].tcp_pose(q)[:3, 3])
            closed.append(bool(state[n].get("grasped", False)))
        verts, tris = merge_meshes(meshes)
        return verts, tris, np.stack(tcp), np.asarray(closed)


@dataclass
class WorkerStats:
    """Counters the worker logs and returns."""

    frames: int = 0
    skipped: int = 0
    published: int = 0
    initialisations: int = 0
    lost: int = 0
    busy_s: float = 0.0


def keypoint_message(out: PipelineOutput, frame_number: int, stamp: float, run: dict[str, Any], ms: float) -> bytes:
    """The ``keypoints`` message of one processed frame."""
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
            "rest_lengths": np.round(topo.rest, 6).tolist() if topo is not None and len(out.keypoints) else [],
            "n_points": out.n_points, "processing_ms": round(ms, 2), "note": out.note,
            "run_index": run.get("run_index"),
        },
    )


class Worker:
    """Subscribes, tracks, publishes; ``run`` until ``stop`` is set."""

    def __init__(self, config: Any, connect: list[str] | None = None) -> None:
        from orchestrator.bus import Bus, local_endpoints

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
        self.pipeline: LivePipeline | None = None
        self._run_key: tuple | None = None
        self._last_frame: int | None = None
        self.stats = WorkerStats()
        self.malformed = OncePerKind(log, "ignored a malformed frame message")

    def _on_state(self, sample: Any) -> None:
        from tdcommon.wire import decode_json

        try:
            msg = decode_json(sample.payload.to_bytes())
        except ValueError:
            return
        with self._lock:
            self._state = msg

    def _pipeline_for(self, run: dict[str, Any], K: np.ndarray, T: np.ndarray) -> LivePipeline:
        key = (run.get("run_index"), run.get("object"), tuple(np.round(T, 6).ravel()))
        if self.pipeline is None or key != self._run_key:
            category = run.get("category")
            params = tracking_params(self.config.tracking, category, run.get("n_keypoints"))
            self.pipeline = LivePipeline(params, K, T, DIMENSION.get(category))
            self._run_key = key
            log.info("new program run %s: tracking %s (%s)", run.get("run_index"), run.get("object"), category)
        return self.pipeline

    def step(self) -> bool:
        """Process the newest frame if there is one; False when none was waiting."""
        from tdcommon.wire import decode_frame

        sample = self.frame_sub.try_recv()
        if sample is None:
            return False
        t0 = time.perf_counter()
        try:
            msg = decode_frame(sample.payload.to_bytes())
        except Exception as e:  # a malformed frame message: counted, logged once per kind (no traceback)
            self.malformed.report(type(e).__name__, str(e)[:200])
            return True
        frame = msg.frame
        if self._last_frame is not None and frame.frame_number > self._last_frame + 1:
            self.stats.skipped += frame.frame_number - self._last_frame - 1  # ring channel: newest wins
        self._last_frame = frame.frame_number
        pipe = self._pipeline_for(msg.run, frame.intrinsics.K, msg.T_world_cam)
        with self._lock:
            state = msg.joint_state or self._state  # the arms at the frame's capture time, when paired
        V = F = tcp = closed = None
        if state is not None:
            V, F, tcp, closed = self.arms.from_state(state)
        before = pipe.state
        out = pipe.process(frame.depth_m(), V, F, tcp, closed)
        if out.status == "init":
            self.stats.initialisations += 1
        if out.status == "lost":
            self.stats.lost += 1
        ms = (time.perf_counter() - t0) * 1e3
        self.bus.put(self.key_out, keypoint_message(out, frame.frame_number, frame.device_stamp, msg.run, ms))
        self.stats.frames += 1
        self.stats.published += 1
        self.stats.busy_s += ms / 1e3
        if before != pipe.state:
            log.info("frame %d: %s -> %s %s", frame.frame_number, before, pipe.state, out.note)
        return True

    def run(self, stop: threading.Event, max_frames: int | None = None) -> WorkerStats:
        """Poll with ``try_recv`` (a thread blocked in ``recv`` would make undeclare abort) until stopped."""
        last_log = time.monotonic()
        while not stop.is_set() and (max_frames is None or self.stats.frames < max_frames):
            try:
                busy = self.step()
            except Exception:  # one bad frame must not end the worker
                log.exception("frame failed")
                busy = True
            if not busy:
                time.sleep(0.002)
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
    ap.add_argument("-v", "--verbose", action="store_true")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        config = load_config(args.config)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    worker = Worker(config, args.connect)
    try:
        stats = worker.run(stop, args.max_frames)
    finally:
        worker.close()
    print(f"worker: {stats.frames} frames ({stats.skipped} skipped), {stats.initialisations} initialisations, "
          f"{stats.lost} lost, mean {1e3 * stats.busy_s / max(1, stats.frames):.1f} ms/frame", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
