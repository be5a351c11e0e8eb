"""Pydantic models of the devices' configuration: one model per driver ``type``.

These are the single source of truth for driver settings (defaults, units, validation);
:mod:`orchestrator.config` composes them into a station. Units: metres, seconds, radians.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from tdcommon.objects import Category
from tdcommon.robot import HOME_Q


class StrictModel(BaseModel):
    """Base for every config model: unknown keys are errors (a typo must not pass silently)."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class Pose(StrictModel):
    """A rigid transform parent <- child: translation (m) then roll-pitch-yaw (rad, extrinsic XYZ)."""

    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """(4, 4) float64 homogeneous transform."""
        from scipy.spatial.transform import Rotation

        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", self.rpy).as_matrix()
        T[:3, 3] = self.xyz
        return T

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> Pose:
        """Inverse of :meth:`matrix`."""
        from scipy.spatial.transform import Rotation

        rpy = Rotation.from_matrix(np.asarray(T)[:3, :3]).as_euler("xyz")
        return cls(xyz=tuple(float(v) for v in T[:3, 3]), rpy=tuple(float(v) for v in rpy))


JointVector = Annotated[list[float], Field(min_length=7, max_length=7)]


# ---------------------------------------------------------------- arms
class _ArmBase(StrictModel):
    base: Pose = Field(default_factory=Pose, description="robot base in the world frame (calibration)")
    home: JointVector = Field(
        default=list(HOME_Q),
        description="joint configuration the arm starts from and returns to, rad",
    )


class FakeArmFault(StrictModel):
    """A scheduled fault of a simulated arm (mock only; soak tests inject faults into a daemon run as a
    subprocess this way): from ``at_wall`` on, the next or current motion stops with a reflex
    (``DeviceError``) until the session recovers the arm. A fault whose time passes while the arm is
    not driven (no motion started or waited on) does not fire."""

    at_wall: float = Field(gt=0.0, description="wall-clock time the fault starts, Unix s")
    kind: Literal["reflex"] = "reflex"
    recoverable: bool = True


class FakeArmConfig(_ArmBase):
    """A simulated Panda that follows commanded trajectories exactly, with optional lag and noise."""

    type: Literal["fake"] = "fake"
    lag: float = Field(0.0, ge=0.0, le=1.0, description="first-order tracking lag, s")
    noise: float = Field(0.0, ge=0.0, le=0.01, description="joint measurement noise std, rad")
    state_rate: float = Field(250.0, ge=100.0, le=2000.0, description="joint state rate, Hz")
    faults: tuple[FakeArmFault, ...] = Field((), description="scheduled reflexes (mock fault injection)")


class FrankaArmConfig(_ArmBase):
    """A Franka Emika Panda through franky-control (FCI)."""

    type: Literal["franka"] = "franka"
    host: str = Field(description="FCI IP address or hostname of the robot controller")
    relative_dynamics: float = Field(0.5, gt=0.0, le=1.0, description="franky's dynamics factor")
    recover_on_reflex: bool = True
    segment_dynamics: bool = Field(
        True, description="apply each segment's limit_scale as its waypoint acceleration/jerk factor"
    )
    start_tolerance: float = Field(
        0.05, gt=0.0, le=0.5, description="max joint distance between motion start and current state, rad"
    )


class URArmConfig(_ArmBase):
    """A Universal Robots arm through ur-rtde (6 joints; the 7th program joint is ignored)."""

    type: Literal["ur"] = "ur"
    host: str = Field(description="robot controller IP address or hostname")
    servo_rate: float = Field(500.0, ge=125.0, le=500.0, description="servoJ streaming rate, Hz")
    lookahead_time: float = Field(0.1, ge=0.03, le=0.2, description="servoJ lookahead, s")
    gain: float = Field(300.0, ge=100.0, le=2000.0, description="servoJ proportional gain")
    start_tolerance: float = Field(
        0.05, gt=0.0, le=0.5, description="max joint distance between motion start and current state, rad"
    )


ArmConfig = Annotated[FakeArmConfig | FrankaArmConfig | URArmConfig, Field(discriminator="type")]


# ---------------------------------------------------------------- grippers
class FakeGripperConfig(StrictModel):
    """A simulated parallel gripper that grasps whatever lies between its fingers."""

    type: Literal["fake"] = "fake"
    max_width: float = Field(0.08, gt=0.0, le=0.2, description="m")
    speed: float = Field(0.1, gt=0.0, le=1.0, description="finger speed, m/s")


class FrankaHandConfig(StrictModel):
    """The Franka Hand of a Panda arm (through franky; uses the arm's host)."""

    type: Literal["franka_hand"] = "franka_hand"
    speed: float = Field(0.05, gt=0.0, le=0.2, description="m/s")
    force: float = Field(20.0, gt=0.0, le=70.0, description="grasp force, N")
    host: str | None = Field(None, description="FCI host; the arm's host (passed by the station) when omitted")
    home_on_connect: bool = Field(True, description="run the finger homing on connect (calibrates the width)")


class SerialGripperConfig(StrictModel):
    """A Robotiq 2F-style gripper speaking Modbus RTU over a serial port."""

    type: Literal["serial"] = "serial"
    port: str = Field(description="serial device, e.g. /dev/ttyUSB0")
    baudrate: int = 115200
    slave_id: int = Field(9, ge=1, le=247)
    timeout: float = Field(0.2, gt=0.0, le=5.0, description="per-request timeout, s")
    retries: int = Field(3, ge=0, le=10)
    stroke: float = Field(0.085, gt=0.0, le=0.2, description="full opening, m")
    open_position: int = Field(
        13, ge=0, le=254,
        description="gPO with the fingers fully open (the 2F-85 manual's example reads 13 at the software limit)",
    )
    closed_position: int = Field(
        226, ge=1, le=255,
        description="gPO with the fingers fully closed on nothing (open_position + stroke / the manual's 0.4 mm "
                    "position resolution); read it off a full close to calibrate one gripper",
    )
    speed: float = Field(0.1, gt=0.0, le=0.5, description="default finger speed, m/s")
    force: float = Field(40.0, gt=0.0, le=500.0, description="default grasp force, N")
    min_speed: float = Field(0.02, gt=0.0, le=0.5, description="finger speed at register 0, m/s")
    max_speed: float = Field(0.15, gt=0.0, le=0.5, description="finger speed at register 255, m/s")
    min_force: float = Field(20.0, ge=0.0, le=500.0, description="grip force at register 0, N")
    max_force: float = Field(235.0, gt=0.0, le=500.0, description="grip force at register 255, N")
    activation_timeout: float = Field(5.0, gt=0.0, le=30.0, description="wait for activation, s")
    state_period: float = Field(
        0.02, ge=0.0, le=1.0, description="reuse a status read this recent instead of a new Modbus request, s"
    )

    @model_validator(mode="after")
    def _positions_ordered(self) -> SerialGripperConfig:
        if self.closed_position <= self.open_position:
            raise ValueError(f"closed_position ({self.closed_position}) must be above open_position "
                             f"({self.open_position})")
        return self


GripperConfig = Annotated[
    FakeGripperConfig | FrankaHandConfig | SerialGripperConfig, Field(discriminator="type")
]


# ---------------------------------------------------------------- cameras
class _CameraBase(StrictModel):
    id: str = Field("cam0", pattern=r"^[A-Za-z0-9_\-]+$", description="used in zenoh keys and channels")
    width: int = Field(1280, ge=64, le=4096)
    height: int = Field(720, ge=48, le=4096)
    fps: float = Field(30.0, gt=0.0, le=120.0)
    pose: Pose = Field(default_factory=Pose, description="camera optical frame in the world (hand-eye)")


class FakeCameraStall(StrictModel):
    """A scheduled stall of a simulated camera (mock only): no frame captured in
    [``at_wall``, ``at_wall`` + ``seconds``), so reads time out and frame_number jumps over the window."""

    at_wall: float = Field(gt=0.0, description="wall-clock time the stall starts, Unix s")
    seconds: float = Field(gt=0.0, le=600.0, description="stall length, s")


class FakeCameraConfig(_CameraBase):
    """A camera that renders the simulated scene with a realistic depth error model."""

    type: Literal["fake"] = "fake"
    hfov_deg: float = Field(69.0, gt=10.0, lt=170.0, description="horizontal field of view, degrees")
    depth_noise: float = Field(0.0015, ge=0.0, le=0.05, description="depth noise std at 1 m, m (grows ~z^2)")
    edge_dropout: float = Field(0.5, ge=0.0, le=1.0, description="probability a depth-edge pixel is lost")
    flying_pixels: float = Field(0.001, ge=0.0, le=0.05, description="fraction of pixels that fly")
    clutter: int = Field(6, ge=0, le=50, description="number of background boxes")
    queue_depth: int = Field(
        6, ge=1, le=64, description="frames kept for a late reader, like a device's frame queue (older ones drop)"
    )
    clock_offset: float = Field(0.0, ge=-1e6, le=1e6, description="simulated device clock minus host clock at "
                                "host time 0, s")
    clock_drift_ppm: float = Field(0.0, ge=-1000.0, le=1000.0, description="simulated device clock rate error, ppm")
    latency: float = Field(0.0, ge=0.0, le=1.0, description="simulated delay from capture to arrival at the host, s")
    latency_jitter: float = Field(0.0, ge=0.0, le=0.5, description="simulated extra arrival delay, uniform in "
                                  "[0, this], s")
    seed: int = 0
    stalls: tuple[FakeCameraStall, ...] = Field((), description="scheduled stalls (mock fault injection)")
    render: Literal["auto", "inline", "process"] = Field(
        "auto", description="where frames are rendered: 'process' in a child process (its CPU off the daemon's "
        "interpreter lock, as a real camera's work is), 'inline' on the reading thread; 'auto': process under the "
        "real clock, inline in simulated time (no start-up cost, everything in one process)")


class RealSenseCameraConfig(_CameraBase):
    """An Intel RealSense D4xx through pyrealsense2 (depth aligned to colour)."""

    type: Literal["realsense"] = "realsense"
    serial: str | None = Field(None, description="device serial; first device when omitted")
    laser_power: float | None = Field(None, ge=0.0, le=360.0, description="mW; device default when omitted")
    start_timeout: float = Field(5.0, gt=0.0, le=60.0, description="wait for the first frame on connect, s")


class OakCameraConfig(_CameraBase):
    """A Luxonis OAK-D through depthai (stereo depth aligned to the colour camera)."""

    type: Literal["oak"] = "oak"
    device_id: str | None = Field(None, description="MxId / device name; first device when omitted")
    start_timeout: float = Field(10.0, gt=0.0, le=60.0, description="wait for the first frame on connect, s")


class ReplayCameraConfig(_CameraBase):
    """Frames played back from an episode MCAP file or a folder in the paper's layout."""

    type: Literal["replay"] = "replay"
    path: str = Field(description="episode .mcap, folder of episodes, or folder with rgbd.npz")
    loop: bool = False


CameraConfig = Annotated[
    FakeCameraConfig | RealSenseCameraConfig | OakCameraConfig | ReplayCameraConfig,
    Field(discriminator="type"),
]


# ---------------------------------------------------------------- simulated object (mock mode)
class SimObjectConfig(StrictModel):
    """The deformable object the simulator builds, holds in the fake grippers and renders."""

    category: Category = Field("dlo", description="what the simulator builds; in a plan, the object's category")
    length: float = Field(0.7, gt=0.05, le=3.0, description="rope / trunk length, or cloth width, m")
    width: float = Field(0.35, gt=0.05, le=2.0, description="cloth height (cloth only), m")
    branch_length: float = Field(0.25, gt=0.02, le=1.5, description="side branch length (branched rope), m")
    radius: float = Field(0.008, gt=0.001, le=0.05, description="rope radius or cloth half thickness, m")
    spacing: float = Field(0.02, gt=0.002, le=0.1, description="particle spacing of the simulation, m")
    bending: float = Field(0.05, ge=0.0, le=1.0, description="bending stiffness, 0 = limp")
    color: tuple[int, int, int] = Field((205, 70, 40), description="RGB")
    seed: int = 0
