"""The simulated station: fake arms, grippers and camera sharing one simulated object and clock.

:class:`SimStation` owns the object simulation and advances it *lazily*: whenever a device needs
the scene at time ``t`` (a camera frame, a gripper's grasp state) the physics catches up to ``t``
on a fixed 300 Hz grid, using the arms' joint states and the grippers' openings at those times. The
devices implement the Protocols of :mod:`drivers.base` and register with the station on
construction by name ("left" / "right"). Everything is timed on the injected :class:`Clock`,
so with a ``SimClock`` a run is deterministic and as fast as the CPU allows.

One module (~700 lines) on purpose: the four devices and the station share one lock, one clock and
the station's lazily advanced simulation; each device is a thin view of it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
import zlib
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from drivers.base import DeviceError
from drivers.clock import Clock, RealClock
from drivers.config import FakeArmConfig, FakeCameraConfig, FakeGripperConfig, SimObjectConfig
from drivers.fake.render import DEPTH_SCALE, SceneRenderer
from drivers.fake.render_process import RenderProcess
from drivers.fake.sim_object import SimGroundTruth, SimObject
from tdcommon.meshes import Mesh, sheet_mesh, tube_mesh
from tdcommon.robot import PandaKinematics
from tdcommon.types import CameraIntrinsics, GripperState, JointMotion, JointState, RGBDFrame

PHYSICS_RATE = 300  # Hz; physics substeps on a fixed grid of absolute times (SimObject.max_substep)
SUBSTEPS_PER_CHUNK = 1  # TCP poses from FK at every substep: results independent of the query pattern
START_TOLERANCE = 0.02  # rad; a motion must start this close to the arm's current joints
SIM_LAG_LIMIT_S = 3.0  # s; a streaming fake camera this far behind real time skips frames
log = logging.getLogger(__name__)


class SimStation:
    """The simulated world: one deformable object, the registered arms/grippers/cameras, one clock.

    obj: the object to build; clock: shared time; seed: offsets the object's seed (determinism).
    The object is created lazily at the first query, but as of the construction time: hanging
    from the TCPs of the closed grippers' arms at that time, settled.
    """

    def __init__(
        self,
        obj: SimObjectConfig,
        clock: Clock,
        seed: int = 0,
        *,
        n_keypoints: int | None = None,
        settle_time: float = 1.5,
    ) -> None:
        self.clock = clock
        self.seed = int(seed)
        self.settle_time = float(settle_time)
        self.arms: dict[str, FakeArm] = {}
        self.grippers: dict[str, FakeGripper] = {}
        self.cameras: dict[str, FakeCamera] = {}
        self._lock = threading.RLock()
        self._obj_config = obj
        self._n_keypoints = n_keypoints
        self._sim: SimObject | None = None
        self._t_origin = float(clock.now())
        self.time = self._t_origin
        self._step_index = 0
        self._contact = False

    # ------------------------------------------------------------ registration
    def add_arm(self, arm: FakeArm) -> None:
        """Register an arm under its name (its TCP drives the gripper of the same name)."""
        with self._lock:
            self.arms[arm.name] = arm

    def add_gripper(self, gripper: FakeGripper) -> None:
        """Register a gripper under its name (mounted on the arm of the same name)."""
        with self._lock:
            self.grippers[gripper.name] = gripper

    def add_camera(self, camera: FakeCamera) -> None:
        """Register a camera under its id."""
        with self._lock:
            self.cameras[camera.id] = camera

    def set_object(self, obj: SimObjectConfig, n_keypoints: int | None = None) -> None:
        """Swap the object: the new one is hung from the grippers at the next query."""
        with self._lock:
            self._obj_config, self._n_keypoints, self._sim = obj, n_keypoints, None
            self._t_origin = float(self.clock.now())

    # ------------------------------------------------------------ simulation
    @property
    def object_config(self) -> SimObjectConfig:
        """The configuration of the current object."""
        return self._obj_config

    @property
    def sim(self) -> SimObject:
        """The object simulation (created and settled on first use)."""
        with self._lock:
            if self._sim is None:
                self._create_object()
            assert self._sim is not None
            return self._sim

    def _gripper_names(self) -> list[str]:
        """Names of the hands that can hold the object, "left" first, then "right", then others."""
        names = set(self.arms)
        order = {"left": 0, "right": 1}
        return sorted(names, key=lambda n: (order.get(n, 2), n))

    def _create_object(self) -> None:
        """Build the object hanging from the closed grippers' TCPs at the current time and settle it."""
        cfg = self._obj_config
        if self.seed:
            cfg = cfg.model_copy(update={"seed": cfg.seed + self.seed})
        sim = SimObject(cfg, self._n_keypoints)
        t = self._t_origin  # the object exists from construction (or swap), whenever first queried
        holders = [
            (n, self.arms[n].tcp_at(t))
            for n in self._gripper_names()
            if n not in self.grippers or self.grippers[n].commanded_closed
        ]
        sim.reset(holders[:2], settle_time=self.settle_time)
        self._step_index = math.floor(t * PHYSICS_RATE + 1e-6)
        self._sim, self.time, self._contact = sim, self._step_index / PHYSICS_RATE, False
        for g in self.grippers.values():
            g._sync_start(t)  # noqa: SLF001 - the station owns the grippers' contact state

    def _closed_at(self, name: str, t: float) -> bool:
        """Whether the hand ``name`` pinches the object at ``t`` (no gripper device: always closed)."""
        g = self.grippers.get(name)
        return True if g is None else g.pinching_at(t)

    def advance_to(self, t: float) -> None:
        """Run the physics up to the last substep-grid time <= ``t`` (never goes back).

        The physics runs on a fixed grid of absolute times (multiples of 1/PHYSICS_RATE s), so
        its result does not depend on when or how often devices query it.
        """
        with self._lock:
            sim = self.sim
            target = math.floor(float(t) * PHYSICS_RATE + 1e-6)
            names = self._gripper_names()
            while self._step_index < target:
                n = min(SUBSTEPS_PER_CHUNK, target - self._step_index)
                t_next = (self._step_index + n) / PHYSICS_RATE
                poses = {name: self.arms[name].tcp_at(t_next) for name in names}
                closed = {name: self._closed_at(name, t_next) for name in names}
                sim.step(n / PHYSICS_RATE, poses, closed)
                self._step_index += n
                self.time = t_next
                self._contact |= bool((sim.x[:, 2] <= sim.radius * 1.05).any())

    # ------------------------------------------------------------ queries
    def ground_truth(self) -> SimGroundTruth:
        """Ground truth of the object at the station's current sim time."""
        with self._lock:
            return self.sim.ground_truth(tuple(self._gripper_names()))

    def grasp_indices(self) -> dict[str, int]:
        """Gripper name -> index of the keypoint it holds (-1: none), now."""
        return dict(self.ground_truth().grasp)

    def holds(self, name: str) -> bool:
        """Whether gripper ``name`` holds the object (at the station's current sim time)."""
        with self._lock:
            return name in self.sim.held

    def episode_facts(self) -> dict[str, Any]:
        """Facts for an episode's metadata since the previous call: grasps, table contact, stretch."""
        with self._lock:
            sim = self.sim
            facts = {
                "sim_category": sim.category,
                "grasp_indices": self.grasp_indices(),
                "contact": self._contact,
                "sim_max_stretch": float(sim.stretch_ratio().max()),
                "sim_time": self.time,
            }
            self._contact = False
            return facts

    def object_mesh(self) -> Mesh:
        """The object's surface now: a tube per chain (ropes) or a closed sheet (cloth)."""
        with self._lock:
            sim = self.sim
            topo = sim.topology
            if topo.grid_shape is not None:
                return sheet_mesh(sim.x.reshape(*topo.grid_shape, 3), sim.radius)
            parts = [tube_mesh(sim.x[c], sim.radius) for c in topo.chains]
            offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
            return (
                np.concatenate([v for v, _ in parts]),
                np.concatenate([f + o for (_, f), o in zip(parts, offsets, strict=True)]).astype(np.int32),
            )

    def arm_meshes(self, t: float) -> list[Mesh]:
        """Every registered arm's triangles at time ``t`` (fingers at the gripper's opening)."""
        out = []
        for name, arm in list(self.arms.items()):
            g = self.grippers.get(name)
            out.append(arm.meshes_at(t, g.width_at(t) if g is not None else 0.08))
        return out


def wall_to_clock(clock: Clock, wall: float) -> float:
    """Clock time of wall-clock (Unix) time ``wall``, s, mapped at the current instant."""
    return clock.now() + (wall - time.time())


class FakeArm:
    """A simulated Panda following commanded :class:`JointMotion` s (optional first-order lag and noise).

    Faults: :meth:`inject_fault` freezes the arm at a given time; ``wait_motion`` then raises
    :class:`DeviceError` and motion is refused until :meth:`recover`. ``config.faults`` schedules
    such faults at wall-clock times (mapped onto the clock when the arm is created).
    """

    def __init__(
        self,
        config: FakeArmConfig,
        *,
        name: str,
        clock: Clock,
        station: SimStation | None = None,
    ) -> None:
        self.name = name
        self.config = config
        self.clock = clock
        self.kin = PandaKinematics(config.base.matrix())
        self._lock = threading.RLock()
        self._hold = np.asarray(config.home, dtype=np.float64)
        self._motion: JointMotion | None = None
        self._t0 = 0.0
        self._fault_at: float | None = None
        self._fault_recoverable = True
        self._fault_message = ""
        self._schedule = sorted(
            ((wall_to_clock(clock, f.at_wall), f.recoverable) for f in config.faults), key=lambda e: e[0]
        )
        self._connected = False
        self._rng = np.random.default_rng(zlib.crc32(name.encode()))  # seeded per arm name
        self._lag_t: float | None = None
        self._lag_q = self._hold.copy()
        if station is not None:
            station.add_arm(self)

    # ------------------------------------------------------------ true state
    def _command_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Commanded (q, dq) at time ``t``; a fault freezes the command at the fault time."""
        frozen = self._fault_at is not None and t >= self._fault_at
        if frozen:
            t = float(self._fault_at)  # type: ignore[arg-type]
        if self._motion is None:
            return self._hold.copy(), np.zeros(7)
        q, dq = self._motion.sample(t - self._t0)
        return (q, np.zeros(7)) if frozen else (q, dq)

    def state_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """True (noise-free) joint position (7,) rad and velocity (7,) rad/s at time ``t``."""
        with self._lock:
            lag = self.config.lag
            if lag <= 0.0:
                return self._command_at(t)
            if self._lag_t is None:
                self._lag_t = t
                self._lag_q = self._command_at(t)[0]
            h = 1.0 / self.config.state_rate
            alpha = 1.0 - math.exp(-h / lag)
            while self._lag_t + h <= t + 1e-12:  # integrate the first-order lag at the state rate
                self._lag_t += h
                self._lag_q = self._lag_q + alpha * (self._command_at(self._lag_t)[0] - self._lag_q)
            q_cmd, _ = self._command_at(t)
            return self._lag_q.copy(), (q_cmd - self._lag_q) / lag

    def tcp_at(self, t: float) -> np.ndarray:
        """(4, 4) world <- TCP at time ``t``."""
        return self.kin.tcp_pose(self.state_at(t)[0])

    def meshes_at(self, t: float, finger_width: float) -> Mesh:
        """The arm's triangles at time ``t``: vertices (V, 3) m world frame, triangles (F, 3)."""
        return self.kin.world_meshes(self.state_at(t)[0], finger_width)

    # ------------------------------------------------------------ Arm protocol
    def connect(self) -> None:
        """Nothing to reach: mark connected."""
        self._connected = True

    def close(self) -> None:
        """Stop any motion (idempotent)."""
        if self._connected:
            self.stop()
        self._connected = False

    def read_state(self) -> JointState:
        """Joint state at the latest state tick (``state_rate`` grid) before now, with measurement noise."""
        now = self.clock.now()
        stamp = math.floor(now * self.config.state_rate + 1e-6) / self.config.state_rate
        q, dq = self.state_at(stamp)
        if self.config.noise > 0:
            with self._lock:
                q = q + self._rng.normal(0.0, self.config.noise, 7)
        return JointState(stamp=stamp, q=q, dq=dq)

    def _arm_scheduled(self, now: float) -> None:
        """Make the next scheduled fault the pending one when none is pending; skip those already past."""
        while self._fault_at is None and self._schedule:
            at, recoverable = self._schedule.pop(0)
            if at >= now:
                self._fault_at, self._fault_recoverable = at, recoverable
                self._fault_message = "scheduled reflex (config faults)"

    def _check_fault(self, now: float) -> None:
        self._arm_scheduled(now)
        if self._fault_at is not None and now >= self._fault_at:
            raise DeviceError(f"{self.name} arm: {self._fault_message}", recoverable=self._fault_recoverable)

    def start_motion(self, motion: JointMotion) -> None:
        """Begin ``motion`` now; DeviceError when faulted, busy or not starting at the current joints."""
        with self._lock:
            now = self.clock.now()
            self._check_fault(now)
            if self._motion is not None and now < self._t0 + self._motion.duration - 1e-9:
                raise DeviceError(f"{self.name} arm: a motion is already running", recoverable=True)
            q_now = self.state_at(now)[0]
            gap = np.abs(np.asarray(motion.q[0]) - q_now)
            if gap.max() > START_TOLERANCE:
                j = int(np.argmax(gap))
                raise DeviceError(
                    f"{self.name} arm: motion starts {gap[j]:.4f} rad away from the current joint {j + 1} "
                    f"({motion.q[0][j]:.4f} vs {q_now[j]:.4f} rad)",
                    recoverable=True,
                )
            self._hold = self._command_at(now)[0]
            self._motion, self._t0 = motion, now

    def wait_motion(self, timeout: float) -> bool:
        """Sleep (on the clock) until the motion ends (True), ``timeout`` s pass (False) or a fault (raise)."""
        start = self.clock.now()
        deadline = start + timeout
        while True:
            with self._lock:
                now = self.clock.now()
                self._check_fault(now)
                end = self._t0 + self._motion.duration if self._motion is not None else now
                if end <= now:
                    return True
                if now >= deadline:
                    return False
                target = min(end, deadline)
                if self._fault_at is not None:
                    target = min(target, max(self._fault_at, now))
            # Short steps so a stop() or fault from another thread is noticed under a real clock.
            self.clock.sleep_until(min(target, now + 0.05))

    def stop(self) -> None:
        """Stop at once: hold the current joint positions."""
        with self._lock:
            now = self.clock.now()
            if self._fault_at is not None and now >= self._fault_at:
                return  # already frozen by the fault
            self._hold = self.state_at(now)[0]
            self._motion = None
            self._lag_q, self._lag_t = self._hold.copy(), now

    def recover(self) -> None:
        """Clear an injected recoverable fault; the arm then holds where it froze."""
        with self._lock:
            now = self.clock.now()
            if self._fault_at is None or now < self._fault_at:
                return
            if not self._fault_recoverable:
                raise DeviceError(f"{self.name} arm: fault is not recoverable", recoverable=False)
            frozen = self._command_at(now)[0]
            self._fault_at = None
            self._hold, self._motion = frozen, None

    def guide_to(self, q: np.ndarray) -> None:
        """Put the arm at joints ``q`` (7,) rad at once, as a hand guiding it would (teaching); refused mid-motion."""
        with self._lock:
            now = self.clock.now()
            if self._motion is not None and now < self._t0 + self._motion.duration - 1e-9:
                raise DeviceError(f"{self.name} arm: cannot be guided while a motion runs", recoverable=True)
            q = np.asarray(q, dtype=np.float64).reshape(7).copy()
            self._hold, self._motion = q, None
            self._lag_q, self._lag_t = q.copy(), now

    # ------------------------------------------------------------ fault injection
    def inject_fault(self, at_time: float, recoverable: bool = True, message: str = "injected reflex") -> None:
        """From clock time ``at_time`` on, freeze the arm and make wait_motion/start_motion raise DeviceError."""
        with self._lock:
            self._fault_at = float(at_time)
            self._fault_recoverable = bool(recoverable)
            self._fault_message = message

    @property
    def faulted(self) -> bool:
        """Whether an injected fault is active now."""
        return self._fault_at is not None and self.clock.now() >= self._fault_at


class FakeGripper:
    """A simulated parallel gripper: fingers move at ``speed``; closing grasps what lies between them."""

    def __init__(
        self,
        config: FakeGripperConfig,
        *,
        name: str,
        clock: Clock,
        station: SimStation | None = None,
    ) -> None:
        self.name = name
        self.config = config
        self.clock = clock
        self.station = station
        self._lock = threading.RLock()
        self.commanded_closed = station is not None  # mock mode starts holding the object
        self._w0 = 0.0 if self.commanded_closed else config.max_width
        self._t0 = clock.now()
        self._target = self._w0
        self._connected = False
        if station is not None:
            station.add_gripper(self)

    def _sync_start(self, t: float) -> None:
        """Called by the station when it hangs the object: closed fingers rest on the object."""
        with self._lock:
            if self.commanded_closed:
                self._w0, self._t0, self._target = self._stop_width(), t, 0.0

    def _stop_width(self) -> float:
        """Width at which closing fingers stop: the object's diameter when holding it, else 0."""
        st = self.station
        if st is not None and st._sim is not None and self.name in st._sim.held:  # noqa: SLF001
            return 2.0 * st._sim.radius  # noqa: SLF001
        return 0.0

    def width_at(self, t: float) -> float:
        """Finger opening (m) at time ``t``."""
        with self._lock:
            travel = self.config.speed * max(0.0, t - self._t0)
            if self._target >= self._w0:
                return min(self._target, self._w0 + travel)
            return max(self._target, self._w0 - travel, self._stop_width() if self.commanded_closed else 0.0)

    def pinching_at(self, t: float) -> bool:
        """Whether the fingers are closed enough at ``t`` to hold an object (closing and within 1 mm of it)."""
        with self._lock:
            if not self.commanded_closed:
                return False
            r = self.station.object_config.radius if self.station is not None else 0.0
            travel = self.config.speed * max(0.0, t - self._t0)
            return self._w0 - travel <= 2.0 * r + 0.001

    # ------------------------------------------------------------ Gripper protocol
    def connect(self) -> None:
        """Nothing to reach: mark connected."""
        self._connected = True

    def close(self) -> None:
        """Release the connection (the fingers stay where they are)."""
        self._connected = False

    def command(self, closed: bool, width: float | None = None, force: float | None = None) -> None:
        """Start closing (grasp) or opening to ``width`` m (default fully); returns at once."""
        now = self.clock.now()
        if self.station is not None:  # outside our lock: the station takes its lock, then ours
            self.station.advance_to(now)  # the physics catches up with the old command first
        with self._lock:
            w = self.width_at(now)
            self.commanded_closed = bool(closed)
            self._w0, self._t0 = w, now
            self._target = 0.0 if closed else float(min(width or self.config.max_width, self.config.max_width))

    def read_state(self) -> GripperState:
        """Opening and whether the gripper holds the object, now."""
        now = self.clock.now()
        grasped = False
        if self.station is not None and self.commanded_closed:
            self.station.advance_to(now)
            grasped = self.station.holds(self.name)
        return GripperState(stamp=now, width=self.width_at(now), grasped=grasped)


@dataclass
class _Shot:
    """One captured frame of the fake camera, before it reaches the host."""

    index: int  # frame number k, captured at k / fps
    color: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) uint16 depth units
    mask: np.ndarray | None  # (H, W) bool object pixels, if asked
    ground_truth: SimGroundTruth


class FakeCamera:
    """An RGB-D camera rendering the station at ``fps`` on the clock's 1/fps grid, with ground truth.

    Frame k is captured at clock time k / fps and ``frame_number`` is k: a device counter running
    since the clock's epoch, so it continues across reconnects and station rebuilds on one clock.
    ``device_stamp`` is the capture time on the camera's own clock (``clock_offset`` and
    ``clock_drift_ppm`` from the host's); the frame reaches the host ``latency`` (+ up to
    ``latency_jitter``) after capture, when ``host_stamp`` is taken.
    Faults: :meth:`inject_fault` drops the next ``count`` frames ("drop": a gap in frame_number)
    or makes the next read raise :class:`DeviceError` ("error"). ``config.stalls`` schedules stalls at
    wall-clock times (mapped onto the clock when the camera is created): no frame is captured inside one.

    Two ways to run, same frames: with a render process under the real clock (``config.render``), the
    camera *streams* as a device does: a thread of its own captures every frame into a queue of
    ``queue_depth`` frames and :meth:`read` only takes the oldest one, so the reader's own work never
    delays a capture. A frame rendered late (the host short of CPU) keeps its capture time and arm poses;
    only a simulation more than ``SIM_LAG_LIMIT_S`` behind skips frames. Otherwise :meth:`read` renders
    the frame it returns (simulated time: deterministic).
    """

    def __init__(
        self,
        config: FakeCameraConfig,
        *,
        clock: Clock,
        station: SimStation,
        name: str | None = None,
        render_mask: bool = False,
    ) -> None:
        self.id = config.id
        self.config = config
        self.clock = clock
        self.station = station
        self.name = name or config.id
        self.render_mask = render_mask
        self.last_mask: np.ndarray | None = None  # (H, W) bool object pixels of the last frame, if asked
        self._intrinsics = CameraIntrinsics.from_fov(config.width, config.height, config.hfov_deg)
        self._renderer: SceneRenderer | RenderProcess | None = None
        self._last_index: int | None = None
        self._drops = 0
        self._errors: list[bool] = []
        self._stalls = [(wall_to_clock(clock, s.at_wall), s.seconds) for s in config.stalls]  # (start, length) s
        self._lock = threading.Lock()
        self._cond = threading.Condition()  # the streamed frames: _queue, _stream_error
        self._queue: deque[_Shot] = deque()
        self._stream_error: DeviceError | None = None
        self._stream: threading.Thread | None = None
        self._stop_stream = threading.Event()
        station.add_camera(self)

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Pinhole intrinsics from the configured size and horizontal field of view."""
        return self._intrinsics

    @property
    def streaming(self) -> bool:
        """Whether frames are captured on a thread of the camera's own (render process, real clock)."""
        return self._stream is not None

    def connect(self) -> None:
        """Build the renderer (static scene pre-render, noise pools) and bring the simulation up to now.

        The object is created and settled here rather than at the first read, so the first frame
        costs no more than any other (the result is the same: the physics runs on a fixed grid).
        A render process is waited for here, and a streaming camera starts capturing.
        """
        if self._renderer is None:
            c = self.config
            kwargs: dict[str, Any] = {
                "intrinsics": self._intrinsics, "T_world_cam": c.pose.matrix(), "depth_noise": c.depth_noise,
                "edge_dropout": c.edge_dropout, "flying_pixels": c.flying_pixels, "clutter": c.clutter,
                "seed": c.seed, "object_color": self.station.object_config.color,
            }
            in_process = c.render == "process" or (c.render == "auto" and isinstance(self.clock, RealClock))
            self._renderer = RenderProcess(kwargs, name=f"camera {self.id}") if in_process else SceneRenderer(**kwargs)
            if isinstance(self._renderer, RenderProcess):
                self._renderer.wait_ready()
        self._last_index = None
        self.station.advance_to(self.clock.now())
        if isinstance(self._renderer, RenderProcess) and isinstance(self.clock, RealClock) and self._stream is None:
            with self._cond:
                self._queue.clear()
                self._stream_error = None
            self._stop_stream.clear()
            self._stream = threading.Thread(target=self._produce, args=(self._renderer,),
                                            name=f"fake-camera-{self.id}", daemon=True)
            self._stream.start()

    def close(self) -> None:
        """Stop streaming (idempotent); a render process exits."""
        renderer, self._renderer = self._renderer, None
        self._stop_stream.set()
        if isinstance(renderer, RenderProcess):
            renderer.close()  # also ends a render the capture thread waits for
        if self._stream is not None:
            self._stream.join(5.0)
            self._stream = None

    def inject_fault(self, kind: Literal["drop", "error"] = "error", count: int = 1, recoverable: bool = True) -> None:
        """Drop the next ``count`` frames, or make the next ``count`` reads raise DeviceError."""
        with self._lock:
            if kind == "drop":
                self._drops += int(count)
            else:
                self._errors.extend([recoverable] * int(count))

    def _after_faults(self, k: int) -> int:
        """Frame index ``k`` moved past injected drops and scheduled stalls (nothing is captured in those)."""
        with self._lock:
            k += self._drops
            self._drops = 0
        for start, length in self._stalls:  # a stalled device captures nothing inside the window
            if start <= k / self.config.fps < start + length:
                k = math.ceil((start + length) * self.config.fps - 1e-6)
        return k

    def _scene(self, k: int) -> tuple[SimGroundTruth, list[Mesh], Mesh, np.ndarray]:
        """Frame ``k``'s ground truth, arm meshes, object mesh and object colour (RGB): the arms at its capture
        time, the object as simulated so far."""
        st = self.station
        t_frame = k / self.config.fps
        st.advance_to(t_frame)
        return (st.ground_truth(), st.arm_meshes(t_frame), st.object_mesh(),
                np.asarray(st.object_config.color, dtype=np.float32))  # the colour after set_object too

    def _capture(self, renderer: SceneRenderer | RenderProcess, k: int) -> _Shot:
        """Render frame ``k`` from the station (see :meth:`_scene`)."""
        gt, arms, obj, color = self._scene(k)
        if isinstance(renderer, RenderProcess):
            rgb, depth, mask = renderer.render(arms, obj, object_color=color, frame_index=k,
                                               with_mask=self.render_mask)
        else:
            renderer.object_color = color
            out = renderer.render(arms, obj, frame_index=k, with_mask=self.render_mask)
            rgb, depth, mask = out.color, out.depth, out.mask
        return _Shot(k, rgb, depth, mask, gt)

    def _produce(self, renderer: RenderProcess) -> None:
        """The streaming camera's capture thread: every frame on its time into the queue (older ones fall out)."""
        fps = self.config.fps
        k = math.ceil(self.clock.now() * fps - 1e-6)
        in_flight: deque[tuple[int, SimGroundTruth]] = deque()  # submitted to the render process, in order
        try:
            while True:
                k = self._after_faults(k)
                if self._stop_stream.wait(max(0.0, k / fps - self.clock.now())):
                    return
                gt, arms, obj, color = self._scene(k)
                renderer.submit(arms, obj, object_color=color, frame_index=k, with_mask=self.render_mask)
                in_flight.append((k, gt))
                # Starved of CPU, the simulation renders late, but every frame keeps its capture time (a device's
                # capture does not wait for the host); only a world that cannot keep up at all skips ahead.
                behind = math.floor(self.clock.now() * fps + 1e-6) - k
                if behind > SIM_LAG_LIMIT_S * fps:
                    log.warning("camera %s: the simulation is %.1f s behind real time (CPU): %d frames skipped",
                                self.id, behind / fps, behind)
                    k += behind
                k += 1
                # On time, a frame is collected at once; behind, the next frame's scene is computed here while
                # the render process draws this one (two stages in parallel).
                while in_flight and (len(in_flight) > 1 or k / fps > self.clock.now()):
                    index, truth = in_flight.popleft()
                    self._push(_Shot(index, *renderer.result(), truth))
        except DeviceError as e:
            with self._cond:
                self._stream_error = e
                self._cond.notify_all()

    def _push(self, shot: _Shot) -> None:
        """Queue a captured frame for :meth:`read`; beyond ``queue_depth`` the oldest falls out (a gap)."""
        with self._cond:
            self._queue.append(shot)
            while len(self._queue) > self.config.queue_depth:
                self._queue.popleft()
            self._cond.notify_all()

    def _next_streamed(self, timeout: float) -> _Shot:
        """The oldest frame in the queue, waiting up to ``timeout`` s for one."""
        deadline = self.clock.now() + timeout
        with self._cond:
            if self._last_index is None:  # first read after a connect: frames from now on
                earliest = self.clock.now() * self.config.fps - 1e-6
                while self._queue and self._queue[0].index < earliest:
                    self._queue.popleft()
            while not self._queue:
                if self._stream_error is not None:
                    self._renderer = None  # closed: the reconnect starts a new one
                    raise self._stream_error
                remaining = deadline - self.clock.now()
                if remaining <= 0:
                    raise DeviceError(f"camera {self.id}: no frame within {timeout} s", recoverable=True)
                self._cond.wait(remaining)
            return self._queue.popleft()

    def _next_index(self, timeout: float) -> int:
        """The next unread frame's index, once its capture time has come (rendered by the reader)."""
        fps = self.config.fps
        now = self.clock.now()
        if self._last_index is None:  # first frame: the one captured at or after now
            k = math.ceil(now * fps - 1e-6)
        else:  # the next unread frame, unless it fell out of the device queue meanwhile
            k = max(self._last_index + 1, math.floor(now * fps + 1e-6) - self.config.queue_depth + 1)
        k = self._after_faults(k)
        if k / fps - now > timeout:
            self.clock.sleep_until(now + timeout)
            raise DeviceError(f"camera {self.id}: no frame within {timeout} s", recoverable=True)
        self.clock.sleep_until(k / fps)
        return k

    def read(self, timeout: float = 1.0) -> RGBDFrame:
        """The next unread frame on the 1/fps grid (waiting for its time), rendered from the station.

        A reader later than ``queue_depth`` frames loses the older ones (a gap in frame_number).
        """
        with self._lock:
            renderer = self._renderer
        if renderer is None:
            raise DeviceError(f"camera {self.id}: not connected", recoverable=True)
        fps = self.config.fps
        shot = self._next_streamed(timeout) if self._stream is not None else None
        k = shot.index if shot is not None else self._next_index(timeout)
        with self._lock:
            self._last_index = k
            if self._errors:
                recoverable = self._errors.pop(0)
                raise DeviceError(f"camera {self.id}: injected frame error", recoverable=recoverable)
        if shot is None:
            try:
                shot = self._capture(renderer, k)
            except DeviceError:
                self._renderer = None  # a render process failed and is closed: the reconnect starts a new one
                raise
        self.last_mask = shot.mask
        t_frame = k / fps
        c = self.config
        if c.latency or c.latency_jitter:  # delivered late: the host stamps it on arrival
            jitter = c.latency_jitter * float(np.random.default_rng((c.seed, k)).random())
            self.clock.sleep_until(t_frame + c.latency + jitter)
        return RGBDFrame(
            color=shot.color,
            depth=shot.depth,
            depth_scale=DEPTH_SCALE,
            intrinsics=self._intrinsics,
            device_stamp=self.device_time(t_frame),
            host_stamp=self.clock.now(),
            frame_number=k,
            ground_truth=shot.ground_truth,
        )

    def device_time(self, t: float) -> float:
        """The camera's own clock at host time ``t``, s (``clock_offset`` and ``clock_drift_ppm``)."""
        return self.config.clock_offset + t * (1.0 + self.config.clock_drift_ppm * 1e-6)
