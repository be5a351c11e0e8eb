"""A fake ``franky`` module: Robot/Gripper that record calls and replay motions, reflexes and network loss.

It follows franky-control's Python API (``Robot(host)``, ``relative_dynamics_factor``,
``move(motion, asynchronous=...)``, ``join_motion(timeout)``, ``recover_from_errors()``,
``current_joint_state.position/.velocity``, ``JointWaypoint(target, reference_type,
relative_dynamics_factor, minimum_time: Duration)``, ``Gripper.grasp_async/move_async`` returning
futures with ``wait(timeout)``/``get()``). Motions "run" in real time, ``time_scale`` times
faster, so tests stay short.
"""

from __future__ import annotations

import builtins
import threading
import time
import types
from dataclasses import dataclass, field
from typing import Any

import numpy as np

builtins_exc = builtins.Exception

# Names a double offers that the real franky does not: test bookkeeping and fault injection.
DOUBLE_ONLY = {"builtins_exc", "FrankaException", "make_module", "motion_duration", "DOUBLE_ONLY"}


class FrankaException(builtins_exc):
    """franka::Exception, exported by franky as ``franky.Exception``: the base of libfranka's exceptions."""


class CommandException(FrankaException):
    """franka::CommandException (command refused, e.g. in reflex mode)."""


class ControlException(FrankaException):
    """franka::ControlException (a reflex during a motion)."""


class IncompatibleVersionException(FrankaException):
    """franka::IncompatibleVersionException (wrong wheel for the robot server)."""


class InvalidOperationException(FrankaException):
    """franka::InvalidOperationException."""


class ModelException(FrankaException):
    """franka::ModelException."""


class NetworkException(FrankaException):
    """franka::NetworkException (connection lost)."""


class ProtocolException(FrankaException):
    """franka::ProtocolException."""


class RealtimeException(FrankaException):
    """franka::RealtimeException (no real-time kernel)."""


class GripperException(builtins_exc):
    """franky::GripperException (franky's own, not a franka::Exception)."""


class InvalidMotionTypeException(builtins_exc):
    """franky::InvalidMotionTypeException."""


class MotionReuseException(builtins_exc):
    """franky::MotionReuseException."""


class ReactionRecursionException(builtins_exc):
    """franky::ReactionRecursionException."""


class TorqueSignalTimeoutException(builtins_exc):
    """franky::TorqueSignalTimeoutException."""


class DeskError(builtins_exc):
    """franky.DeskError (Desk web API)."""


class FrankaAPIError(DeskError):
    """franky.FrankaAPIError."""


class TakeControlTimeoutError(DeskError):
    """franky.TakeControlTimeoutError."""


class Duration:
    """franka::Duration: integer milliseconds (``to_msec()`` / ``to_sec()``)."""

    def __init__(self, ms: int = 0) -> None:
        if not isinstance(ms, int):
            raise TypeError("Duration takes integer milliseconds")
        self._ms = ms

    def to_msec(self) -> int:
        return self._ms

    def to_sec(self) -> float:
        return self._ms / 1000.0


class RelativeDynamicsFactor:
    """franky.RelativeDynamicsFactor(velocity, acceleration, jerk)."""

    def __init__(self, velocity: float = 1.0, acceleration: float | None = None, jerk: float | None = None) -> None:
        self.velocity = velocity
        self.acceleration = velocity if acceleration is None else acceleration
        self.jerk = velocity if jerk is None else jerk


class ReferenceType:
    """franky.ReferenceType."""

    Absolute = "Absolute"
    Relative = "Relative"


@dataclass
class JointState:
    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(7))


class JointWaypoint:
    """franky.JointWaypoint (franky >= 1.0 signature: minimum_time is a Duration)."""

    def __init__(self, target: Any, reference_type: Any = ReferenceType.Absolute, relative_dynamics_factor: Any = 1.0,
                 minimum_time: Duration | None = None, hold_target_duration: Duration | None = None,
                 max_total_duration: Duration | None = None) -> None:
        for value in (minimum_time, hold_target_duration, max_total_duration):
            if value is not None and not isinstance(value, Duration):
                raise TypeError("minimum_time / hold_target_duration / max_total_duration must be a Duration")
        position = np.asarray(target.position if isinstance(target, JointState) else target, dtype=float)
        assert position.shape == (7,)
        self.target = JointState(position)
        self.reference_type = reference_type
        if isinstance(relative_dynamics_factor, int | float):  # franky converts a number implicitly
            relative_dynamics_factor = RelativeDynamicsFactor(float(relative_dynamics_factor))
        self.relative_dynamics_factor = relative_dynamics_factor
        self.minimum_time = minimum_time
        self.hold_target_duration = hold_target_duration or Duration(0)
        self.max_total_duration = max_total_duration


class JointWaypointMotion:
    def __init__(self, waypoints: list[JointWaypoint], relative_dynamics_factor: Any = 1.0,
                 return_when_finished: bool = True) -> None:
        self.waypoints = list(waypoints)
        self.relative_dynamics_factor = relative_dynamics_factor
        self.return_when_finished = return_when_finished


class JointStopMotion:
    def __init__(self, relative_dynamics_factor: Any = 1.0) -> None:
        self.relative_dynamics_factor = relative_dynamics_factor


def motion_duration(motion: Any) -> float:
    """How long the double lets ``motion`` run: its waypoints' minimum and hold times (0 for a stop)."""
    return sum((w.minimum_time.to_sec() if w.minimum_time else 0.0) + w.hold_target_duration.to_sec()
               for w in getattr(motion, "waypoints", []))


class Robot:
    """Records every call; a motion completes after its duration / ``time_scale`` (real time)."""

    instances: list[Robot] = []
    time_scale = 20.0
    connect_error: builtins_exc | None = None
    initial_q = np.array([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785])

    DOUBLE_ONLY = {"instances", "time_scale", "connect_error", "initial_q", "calls", "q", "fault", "disconnected",
                   "host"}

    def __init__(self, fci_hostname: str, **kwargs: Any) -> None:
        if Robot.connect_error is not None:
            raise Robot.connect_error
        self.host = self.fci_hostname = fci_hostname
        self.calls: list[tuple[float, str, Any]] = []
        self._rdf: Any = 1.0
        self.q = Robot.initial_q.copy()
        self.has_errors = False
        self.fault: builtins_exc | None = None  # raised by join_motion of the next motion
        self.disconnected = False
        self._done = threading.Event()
        self._done.set()
        self._pending: builtins_exc | None = None
        self._timer: threading.Timer | None = None
        Robot.instances.append(self)

    def _log(self, what: str, arg: Any = None) -> None:
        self.calls.append((time.monotonic(), what, arg))

    @property
    def relative_dynamics_factor(self) -> Any:
        return self._rdf

    @relative_dynamics_factor.setter
    def relative_dynamics_factor(self, value: Any) -> None:
        self._log("relative_dynamics_factor", value)
        self._rdf = value

    @property
    def current_joint_state(self) -> JointState:
        if self.disconnected:
            raise NetworkException("libfranka: UDP receive: Timeout")
        return JointState(self.q.copy(), np.zeros(7))

    def move(self, motion: Any, asynchronous: bool = False) -> None:
        self._log("move", (motion, asynchronous))
        if self.disconnected:
            raise NetworkException("libfranka: connection lost")
        if self._pending is not None:
            exc, self._pending = self._pending, None
            raise exc
        if self.has_errors:
            raise CommandException("libfranka: Move command rejected: command not possible in the current mode")
        self._done.clear()
        fault, self.fault = self.fault, None
        final = motion.waypoints[-1].target.position if getattr(motion, "waypoints", None) else self.q

        def finish() -> None:
            if fault is not None:
                self.has_errors = True
                self._pending = fault
            else:
                self.q = np.array(final, dtype=float)
            self._done.set()

        delay = motion_duration(motion) / Robot.time_scale if fault is None else 0.01
        self._timer = threading.Timer(delay, finish)
        self._timer.daemon = True
        self._timer.start()
        if not asynchronous:
            self.join_motion()

    def join_motion(self, timeout: float | None = None) -> bool:
        self._log("join_motion", timeout)
        done = self._done.wait(timeout)
        if done and self._pending is not None:
            exc, self._pending = self._pending, None
            raise exc
        return done

    def recover_from_errors(self) -> None:
        self._log("recover_from_errors")
        if self.disconnected:
            raise NetworkException("libfranka: connection lost")
        self.has_errors = False

    def stop(self) -> None:
        self._log("stop")


class BoolFuture:
    def __init__(self, value: bool, delay: float = 0.0) -> None:
        self._value = value
        self._ready_at = time.monotonic() + delay

    def wait(self, timeout: float | None = None) -> bool:
        remaining = self._ready_at - time.monotonic()
        if remaining > 0 and (timeout is None or timeout >= remaining):
            time.sleep(remaining)
        return time.monotonic() >= self._ready_at

    def get(self) -> bool:
        self.wait()
        return self._value


@dataclass
class GripperState:
    width: float
    max_width: float
    is_grasped: bool
    temperature: float = 30.0
    time: Duration = field(default_factory=Duration)


class Gripper:
    """franky.Gripper: grasps an object ``object_width`` m wide when closing past it."""

    DOUBLE_ONLY = {"instances", "object_width", "host", "calls", "fail"}
    instances: list[Gripper] = []
    object_width: float | None = 0.02

    def __init__(self, fci_hostname: str) -> None:
        self.host = fci_hostname
        self.calls: list[tuple[str, tuple[Any, ...], dict[str, Any]]] = []
        self.max_width = 0.08
        self.width = 0.0
        self.is_grasped = False
        self.fail = False  # state reads raise GripperException while set
        Gripper.instances.append(self)

    def homing(self) -> bool:
        self.calls.append(("homing", (), {}))
        self.width = self.max_width
        return True

    def grasp_async(self, width: float, speed: float, force: float, epsilon_inner: float = 0.005,
                    epsilon_outer: float = 0.005) -> BoolFuture:
        self.calls.append(("grasp_async", (width, speed, force), {"epsilon_inner": epsilon_inner,
                                                                   "epsilon_outer": epsilon_outer}))
        obj = Gripper.object_width
        if obj is not None and obj < self.width:
            self.width, ok = obj, width - epsilon_inner <= obj <= width + epsilon_outer
        else:
            self.width, ok = width, False
        self.is_grasped = ok
        return BoolFuture(ok)

    def move_async(self, width: float, speed: float) -> BoolFuture:
        self.calls.append(("move_async", (width, speed), {}))
        self.width, self.is_grasped = width, False
        return BoolFuture(True)

    def stop(self) -> bool:
        self.calls.append(("stop", (), {}))
        return True

    @property
    def state(self) -> GripperState:
        time.sleep(0.001)  # libfranka waits for the hand's next state packet
        if self.fail:
            raise GripperException("libfranka gripper: UDP receive: Timeout")
        return GripperState(self.width, self.max_width, self.is_grasped)


def make_module() -> types.ModuleType:
    """A fresh fake ``franky`` module (class-level registries cleared)."""
    Robot.instances = []
    Robot.connect_error = None
    Gripper.instances = []
    Gripper.object_width = 0.02
    mod = types.ModuleType("franky")
    for name, value in list(globals().items()):
        if isinstance(value, type) and value.__module__ == __name__ and name != "FrankaException":
            setattr(mod, name, value)
    mod.Exception = FrankaException
    return mod
