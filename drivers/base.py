"""One ``Protocol`` per device kind and the registry that builds a device from its config.

The registry maps a config ``type`` to ``"module:Class"``; the module is imported only when
a device of that type is built, so vendor SDKs (franky, ur-rtde, pyrealsense2, depthai)
are needed only on stations that use them.
"""

from __future__ import annotations

import importlib
from typing import Any, Protocol, runtime_checkable

from tdcommon.types import CameraIntrinsics, GripperState, JointMotion, JointState, RGBDFrame


class DeviceError(RuntimeError):
    """A device failed; ``recoverable`` says whether a recover() + retry may help."""

    def __init__(self, message: str, *, recoverable: bool = True) -> None:
        super().__init__(message)
        self.recoverable = recoverable


class DriverUnavailable(ImportError):
    """A driver's vendor SDK is not installed; the message says which extra to install."""


@runtime_checkable
class Arm(Protocol):
    """A 7-DoF arm commanded in joint space."""

    name: str

    def connect(self) -> None:
        """Open the connection; raise DeviceError when the arm cannot be reached."""

    def close(self) -> None:
        """Stop any motion and release the connection (idempotent)."""

    def read_state(self) -> JointState:
        """The latest joint state (non-blocking)."""

    def start_motion(self, motion: JointMotion) -> None:
        """Begin executing ``motion`` (returns at once); it must start from the current state."""

    def wait_motion(self, timeout: float) -> bool:
        """Block until the motion ends (True) or ``timeout`` s pass (False); raise DeviceError on a fault."""

    def stop(self) -> None:
        """Stop as soon as possible (decelerating)."""

    def recover(self) -> None:
        """Clear a recoverable fault (e.g. a Franka reflex) so motion can resume."""


@runtime_checkable
class Gripper(Protocol):
    """A parallel gripper."""

    name: str

    def connect(self) -> None:
        """Open the connection."""

    def close(self) -> None:
        """Release the connection (idempotent)."""

    def command(self, closed: bool, width: float | None = None, force: float | None = None) -> None:
        """Start opening (to ``width`` m, or fully) or grasping (with ``force`` N); returns at once."""

    def read_state(self) -> GripperState:
        """The latest gripper state."""


@runtime_checkable
class RGBDCamera(Protocol):
    """A colour + depth camera with depth aligned to colour."""

    id: str

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the (aligned) colour image."""

    def connect(self) -> None:
        """Start streaming."""

    def close(self) -> None:
        """Stop streaming (idempotent)."""

    def read(self, timeout: float = 1.0) -> RGBDFrame:
        """The next frame; raise DeviceError after ``timeout`` s without one."""


_REGISTRY: dict[str, dict[str, str]] = {
    "arm": {
        "fake": "drivers.fake.devices:FakeArm",
        "franka": "drivers.franka:FrankaArm",
        "ur": "drivers.ur:URArm",
    },
    "gripper": {
        "fake": "drivers.fake.devices:FakeGripper",
        "franka_hand": "drivers.franka:FrankaHand",
        "serial": "drivers.serial_gripper:SerialGripper",
    },
    "camera": {
        "fake": "drivers.fake.devices:FakeCamera",
        "realsense": "drivers.realsense:RealSenseCamera",
        "oak": "drivers.oak:OakCamera",
        "replay": "drivers.replay:ReplayCamera",
    },
}


def register(kind: str, type_name: str, target: str) -> None:
    """Add or replace a driver: ``register("camera", "mycam", "mypkg.cam:MyCam")``."""
    if kind not in _REGISTRY:
        raise ValueError(f"unknown device kind {kind!r}; expected one of {sorted(_REGISTRY)}")
    _REGISTRY[kind][type_name] = target


def driver_class(kind: str, type_name: str) -> type:
    """Import and return the class registered for ``kind``/``type_name``."""
    try:
        target = _REGISTRY[kind][type_name]
    except KeyError:
        known = sorted(_REGISTRY.get(kind, {}))
        raise ValueError(f"no {kind} driver of type {type_name!r}; known types: {known}") from None
    module_name, _, attr = target.partition(":")
    module = importlib.import_module(module_name)
    return getattr(module, attr)


def _create(kind: str, config: Any, **context: Any) -> Any:
    return driver_class(kind, config.type)(config, **context)


def create_arm(config: Any, **context: Any) -> Arm:
    """Build the arm driver for ``config`` (an ArmConfig); ``context`` passes e.g. name, clock, station."""
    return _create("arm", config, **context)


def create_gripper(config: Any, **context: Any) -> Gripper:
    """Build the gripper driver for ``config`` (a GripperConfig)."""
    return _create("gripper", config, **context)


def create_camera(config: Any, **context: Any) -> RGBDCamera:
    """Build the camera driver for ``config`` (a CameraConfig)."""
    return _create("camera", config, **context)
