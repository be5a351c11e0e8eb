"""Franka Emika Panda arm and Franka Hand through franky-control (FCI).

A :class:`~tdcommon.types.JointMotion` becomes one franky ``JointWaypointMotion`` over the
segment targets: each ``JointWaypoint`` carries its segment's duration as ``minimum_time``
(franky hands it to ruckig as the segment's ``minimum_duration``) and, when
``segment_dynamics`` is on, the segment's ``limit_scale`` as its acceleration/jerk factor.
franky runs the 1 kHz loop in C++; ``robot.move(..., asynchronous=True)`` returns at once, so
two arms started back to back move together. franky is imported lazily; never import
``pylibfranka`` in the same process (pybind11 type clash).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np

from drivers.base import DeviceError, DriverUnavailable
from drivers.clock import Clock, RealClock
from drivers.config import FrankaArmConfig, FrankaHandConfig
from tdcommon.types import GripperState, JointMotion, JointState

INSTALL_HINT = "pip install 'trackdeform3d[franka]'"

# franky exports libfranka's exceptions with ``franky.Exception`` as their common base, next
# to franky's own (GripperException, MotionReuseException, ...) that derive from Python's
# Exception. The fatal ones are checked first; these can be cleared by
# recover_from_errors() or a reconnect ...
_RECOVERABLE = (
    "ControlException",
    "CommandException",
    "NetworkException",
    "InvalidOperationException",
    "GripperException",
    "MotionReuseException",
    "ReactionRecursionException",
    "InvalidMotionTypeException",
    "TorqueSignalTimeoutException",
    "Exception",
)
# ... these cannot: wrong wheel for the robot's server version, no real-time kernel, bad model.
_FATAL = ("IncompatibleVersionException", "RealtimeException", "ModelException", "ProtocolException")


def import_franky() -> Any:
    """Import franky or raise DriverUnavailable with the install command."""
    if "pylibfranka" in __import__("sys").modules:
        raise DriverUnavailable("pylibfranka is loaded in this process; franky cannot be imported with it")
    try:
        import franky  # lazy: only Franka stations need it
    except ImportError as exc:
        raise DriverUnavailable(f"the Franka driver needs franky-control: {INSTALL_HINT}") from exc
    return franky


def _franky_errors(franky: Any) -> tuple[tuple[type[BaseException], ...], tuple[type[BaseException], ...]]:
    """(recoverable, fatal) exception classes that this franky build defines."""

    def pick(names: tuple[str, ...]) -> tuple[type[BaseException], ...]:
        found = (getattr(franky, n, None) for n in names)
        return tuple(t for t in found if isinstance(t, type) and issubclass(t, BaseException))

    return pick(_RECOVERABLE) + (RuntimeError,), pick(_FATAL)


class _FrankyErrors:
    """Context manager translating franky exceptions into DeviceError."""

    def __init__(self, owner: str, what: str, franky: Any, on_control_error: Any = None) -> None:
        self.owner, self.what = owner, what
        self.recoverable, self.fatal = _franky_errors(franky)
        self.control = getattr(franky, "ControlException", None)
        self.on_control_error = on_control_error

    def __enter__(self) -> None:
        return None

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: Any) -> bool:
        if exc is None or isinstance(exc, DeviceError):
            return False
        if self.fatal and isinstance(exc, self.fatal):
            raise DeviceError(f"{self.owner}: {self.what}: {type(exc).__name__}: {exc}", recoverable=False) from exc
        if isinstance(exc, self.recoverable):
            if self.on_control_error is not None and self.control is not None and isinstance(exc, self.control):
                self.on_control_error()
            raise DeviceError(f"{self.owner}: {self.what}: {type(exc).__name__}: {exc}", recoverable=True) from exc
        return False


def _duration(franky: Any, seconds: float) -> Any:
    """A franky ``Duration`` (integer milliseconds) for ``seconds``."""
    return franky.Duration(int(round(seconds * 1000.0)))


class FrankaArm:
    """One Panda commanded through franky: waypoint motions with per-segment minimum times."""

    def __init__(self, config: FrankaArmConfig, *, name: str = "franka", clock: Clock | None = None,
                 **_: Any) -> None:
        self.config = config
        self.name = name
        self.host = config.host
        self._clock: Clock = clock or RealClock()
        self._franky: Any = None
        self._robot: Any = None
        self._lock = threading.Lock()
        self._moving = False
        self.motion_started_at: float | None = None

    # ------------------------------------------------------------------ helpers
    def _errors(self, what: str, *, reflex_recovery: bool = False) -> _FrankyErrors:
        hook = self._auto_recover if reflex_recovery and self.config.recover_on_reflex else None
        return _FrankyErrors(self.name, what, self._franky, hook)

    def _auto_recover(self) -> None:
        """Clear a reflex right away so the arm is not left locked (the motion still fails)."""
        try:
            self._robot.recover_from_errors()
        except Exception:  # noqa: BLE001 - best effort; recover() reports properly
            pass

    def _require(self) -> Any:
        if self._robot is None:
            raise DeviceError(f"{self.name}: not connected")
        return self._robot

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        """Connect to the FCI, set the dynamics factor, clear old errors and read the state."""
        self._franky = import_franky()
        with self._errors(f"connect to {self.host}"):
            self._robot = self._franky.Robot(self.host)
            self._robot.relative_dynamics_factor = self.config.relative_dynamics
            if getattr(self._robot, "has_errors", False):
                self._robot.recover_from_errors()
        self.read_state()

    def close(self) -> None:
        """Stop any motion and drop the connection (idempotent)."""
        if self._robot is None:
            return
        if self._moving:
            try:
                self.stop()
            except DeviceError:
                pass
        self._robot = None
        self._moving = False

    # ------------------------------------------------------------------ state
    def read_state(self) -> JointState:
        """Joint positions and velocities from franky's latest robot state."""
        robot = self._require()
        with self._errors("read state"):
            js = robot.current_joint_state
            q = np.asarray(js.position, dtype=np.float64).reshape(7)
            dq = np.asarray(js.velocity, dtype=np.float64).reshape(7)
        return JointState(self._clock.now(), q, dq)

    # ------------------------------------------------------------------ motion
    def build_motion(self, motion: JointMotion) -> Any:
        """The franky JointWaypointMotion for ``motion`` (one waypoint per segment).

        A moving segment gets ``minimum_time`` = its duration; a dwell (limit_scale 0 or no
        displacement) is a waypoint at the same target held for its duration.
        """
        franky = self._franky
        waypoints = []
        previous = np.asarray(motion.q[0], dtype=np.float64)[:7]
        for target, duration, scale in zip(motion.targets, motion.durations, motion.limit_scale, strict=True):
            target = np.asarray(target, dtype=np.float64)[:7]
            dwell = scale <= 0.0 or float(np.max(np.abs(target - previous))) < 1e-6
            factor: Any = 1.0
            if self.config.segment_dynamics and not dwell:
                # limit_scale is relative to the arm's full limits; franky multiplies the robot
                # factor in, so divide it out (velocity stays free so the duration can be met).
                a = float(np.clip(scale / self.config.relative_dynamics, 1e-3, 1.0))
                factor = franky.RelativeDynamicsFactor(1.0, a, a)
            waypoints.append(self._waypoint(target.tolist(), factor, float(duration), dwell))
            previous = target
        return franky.JointWaypointMotion(waypoints)

    def _waypoint(self, target: list[float], factor: Any, duration: float, dwell: bool) -> Any:
        """A JointWaypoint reaching ``target`` in at least ``duration`` s (or holding it that long).

        franky >= 1.0 takes ``minimum_time``/``hold_target_duration`` as ``Duration`` (ms);
        earlier 0.x builds took float seconds, so fall back to that when Duration is refused.
        """
        franky = self._franky
        key = "hold_target_duration" if dwell else "minimum_time"
        try:
            return franky.JointWaypoint(target, relative_dynamics_factor=factor,
                                        **{key: _duration(franky, duration)})
        except TypeError:
            return franky.JointWaypoint(target, relative_dynamics_factor=factor, **{key: duration})

    def start_motion(self, motion: JointMotion) -> None:
        """Send the waypoint motion asynchronously (returns at once); it must start here."""
        robot = self._require()
        if len(motion.targets) == 0:
            return
        current = self.read_state().q
        gap = float(np.max(np.abs(np.asarray(motion.q[0], dtype=np.float64)[:7] - current)))
        if gap > self.config.start_tolerance:
            raise DeviceError(f"{self.name}: motion starts {gap:.3f} rad from the current joint state")
        franky_motion = self.build_motion(motion)
        with self._lock, self._errors("start motion", reflex_recovery=True):
            robot.move(franky_motion, asynchronous=True)
            self._moving = True
            self.motion_started_at = self._clock.now()

    def wait_motion(self, timeout: float) -> bool:
        """Join the running motion; a reflex or other franky error raises DeviceError."""
        robot = self._require()
        with self._errors("motion", reflex_recovery=True):
            try:
                done = bool(robot.join_motion(timeout=max(timeout, 0.0)))
            except BaseException:
                self._moving = False
                raise
        if done:
            self._moving = False
        return done

    def stop(self) -> None:
        """Decelerate with a JointStopMotion (same control mode, so it preempts smoothly)."""
        robot = self._require()
        with self._errors("stop"):
            try:
                robot.move(self._franky.JointStopMotion(), asynchronous=True)
                robot.join_motion(timeout=2.0)
            finally:
                self._moving = False

    def recover(self) -> None:
        """Clear a reflex with recover_from_errors(); reconnect when the link itself was lost."""
        if self._franky is None:
            self.connect()
            return
        network = getattr(self._franky, "NetworkException", None)
        try:
            with self._errors("recover"):
                self._require().recover_from_errors()
        except DeviceError as exc:
            if not (exc.recoverable and network is not None and isinstance(exc.__cause__, network)):
                raise
            self._robot = None
            self.connect()
        self._moving = False


class FrankaHand:
    """The Franka Hand through franky.Gripper: asynchronous move/grasp, homing on connect.

    libfranka's gripper state read blocks until the hand's next state packet, so a background
    thread keeps the latest state and read_state() returns it without blocking.
    """

    def __init__(self, config: FrankaHandConfig, *, name: str = "franka_hand", clock: Clock | None = None,
                 arm: Any = None, arm_config: Any = None, host: str | None = None, **_: Any) -> None:
        self.config = config
        self.name = name
        self._clock: Clock = clock or RealClock()
        self.host = config.host or host or _host_of(arm) or _host_of(arm_config)
        self._franky: Any = None
        self._gripper: Any = None
        self._future: Any = None
        self._state: GripperState | None = None
        self._state_error: DeviceError | None = None
        self._state_ready = threading.Event()
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None

    def connect(self) -> None:
        """Connect to the hand (via the arm's FCI host), home the fingers, start the state reader."""
        if not self.host:
            raise DeviceError(f"{self.name}: no host: set gripper.host or build it with arm_config=<the arm's config>",
                              recoverable=False)
        self._franky = import_franky()
        with self._errors(f"connect to {self.host}"):
            self._gripper = self._franky.Gripper(self.host)
            if self.config.home_on_connect:
                self._gripper.homing()
        self._stop.clear()
        self._state_ready.clear()
        self._state_error = None
        self._poller = threading.Thread(target=self._poll, args=(self._gripper,), name=f"{self.name}-state",
                                        daemon=True)
        self._poller.start()
        if not self._state_ready.wait(5.0):
            self.close()
            raise DeviceError(f"{self.name}: no gripper state within 5 s")
        self.read_state()

    def _poll(self, gripper: Any) -> None:
        """Read the hand's state continuously (each read waits for the next packet)."""
        while not self._stop.is_set():
            try:
                with self._errors("read state"):
                    state = gripper.state
                    self._state = GripperState(self._clock.now(), float(state.width), bool(state.is_grasped))
                self._state_error = None
            except DeviceError as exc:
                self._state_error = exc
                self._stop.wait(0.1)
            self._state_ready.set()
            self._stop.wait(0.001)

    def _errors(self, what: str) -> _FrankyErrors:
        return _FrankyErrors(self.name, what, self._franky)

    def close(self) -> None:
        """Stop the state reader and drop the connection (idempotent); the fingers keep their position."""
        self._stop.set()
        poller, self._poller = self._poller, None
        if poller is not None and poller is not threading.current_thread():
            poller.join(timeout=2.0)
        self._gripper = None
        self._future = None

    def command(self, closed: bool, width: float | None = None, force: float | None = None) -> None:
        """Start a grasp (force N, any width) or an opening move to ``width`` m; returns at once."""
        if self._gripper is None:
            raise DeviceError(f"{self.name}: not connected")
        speed = self.config.speed
        with self._errors("command"):
            if closed:
                # grasp an object of unknown width: target 0 with a wide outer tolerance
                target = 0.0 if width is None else float(width)
                self._future = self._gripper.grasp_async(target, speed, self.config.force if force is None else force,
                                                         epsilon_inner=0.005 if width is not None else 1.0,
                                                         epsilon_outer=1.0)
            else:
                target = float(self._gripper.max_width if width is None else width)
                self._future = self._gripper.move_async(target, speed)

    def wait(self, timeout: float) -> bool | None:
        """Result of the last command (None while it still runs after ``timeout`` s)."""
        if self._future is None:
            return True
        with self._errors("command"):
            if not self._future.wait(timeout):
                return None
            return bool(self._future.get())

    def read_state(self) -> GripperState:
        """The latest finger width and grasp flag (non-blocking)."""
        if self._gripper is None or self._state is None:
            raise DeviceError(f"{self.name}: not connected")
        if self._state_error is not None:
            raise self._state_error
        return self._state

    def recover(self) -> None:
        """Stop the fingers and reconnect (the hand has no error state to clear)."""
        gripper = self._gripper
        self.close()
        if gripper is not None:
            try:
                with self._errors("stop"):
                    gripper.stop()
            except DeviceError:
                pass
        self.connect()


def _host_of(arm: Any) -> str | None:
    """The FCI host of an arm driver or arm config (the hand shares it)."""
    if arm is None:
        return None
    host = getattr(arm, "host", None)
    if host is None and getattr(arm, "config", None) is not None:
        host = getattr(arm.config, "host", None)
    return host
