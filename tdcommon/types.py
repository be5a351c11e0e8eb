"""Plain data types exchanged between drivers, the orchestrator and the tracker.

Units are SI: metres, seconds, radians. Images are row-major ``(H, W, ...)`` arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the depth-aligned colour image (no distortion: frames are rectified)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the conventional name
        """(3, 3) float64 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float) -> CameraIntrinsics:
        """Square-pixel intrinsics with the principal point at the image centre."""
        f = 0.5 * width / np.tan(np.deg2rad(hfov_deg) / 2.0)
        return cls(width, height, float(f), float(f), (width - 1) / 2.0, (height - 1) / 2.0)

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int) -> CameraIntrinsics:  # noqa: N802 - the conventional name
        """Intrinsics of a ``width`` x ``height`` image from its (3, 3) camera matrix ``K``."""
        K = np.asarray(K, dtype=np.float64)
        return cls(int(width), int(height), float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

    def scaled(self, width: int, height: int) -> CameraIntrinsics:
        """The same optics at another resolution."""
        sx, sy = width / self.width, height / self.height
        return CameraIntrinsics(width, height, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy)


@dataclass(frozen=True)
class JointState:
    """One arm's joint state.

    q, dq: (7,) float64, rad and rad/s. stamp: host clock, s.
    """

    stamp: float
    q: np.ndarray
    dq: np.ndarray


@dataclass(frozen=True)
class GripperState:
    """Gripper opening width (m), whether it holds something, host stamp (s)."""

    stamp: float
    width: float
    grasped: bool


@dataclass(frozen=True)
class GroundTruth:
    """What the simulator knows about a frame (mock mode only).

    keypoints: (N, 3) float64, metres, world frame: the object's reference keypoints.
    edges: (E, 2) int64 topology of those keypoints.
    centreline: (M, 3) float64 dense samples of the object's centreline (1D) or mid-surface (2D).
    radius: tube radius (1D) or half thickness (2D), m.
    anchors: (A,) int64 indices into keypoints of ends / junctions / corners.
    """

    keypoints: np.ndarray
    edges: np.ndarray
    centreline: np.ndarray
    radius: float
    anchors: np.ndarray
    category: str


@dataclass(frozen=True)
class RGBDFrame:
    """One synchronised colour + depth capture, depth aligned to colour.

    color: (H, W, 3) uint8, RGB. depth: (H, W) uint16, ``depth * depth_scale`` metres, 0 = no data.
    device_stamp / host_stamp: s (device clock / host clock at arrival). frame_number: device counter.
    """

    color: np.ndarray
    depth: np.ndarray
    depth_scale: float
    intrinsics: CameraIntrinsics
    device_stamp: float
    host_stamp: float
    frame_number: int
    ground_truth: GroundTruth | None = field(default=None, compare=False)

    def depth_m(self) -> np.ndarray:
        """(H, W) float32 depth in metres, 0 where missing."""
        return self.depth.astype(np.float32) * np.float32(self.depth_scale)

    def depth_mm(self) -> np.ndarray:
        """(H, W) little-endian uint16 depth in millimetres, 0 where missing (the recorded and exported unit)."""
        if abs(self.depth_scale - 0.001) < 1e-12:
            return self.depth.astype("<u2", copy=False)
        return np.clip(np.round(self.depth.astype(np.float64) * self.depth_scale * 1000.0), 0, 65535).astype("<u2")


@dataclass(frozen=True)
class JointMotion:
    """A timed joint-space motion for one arm, rest to rest at every segment end.

    Every driver gets the same description and uses what suits it: franky replays the
    segment targets with their durations, ur-rtde streams the samples with servoJ, the fake
    arm interpolates the samples.

    times: (K,) float64, s from motion start, uniform step ``dt``.
    q, dq: (K, 7) float64, rad and rad/s.
    targets: (S, 7) float64, rad, the end of each segment. durations: (S,) float64, s.
    limit_scale: (S,) float64, the fraction of the arm's dynamic limits each segment uses.
    """

    times: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    targets: np.ndarray
    durations: np.ndarray
    limit_scale: np.ndarray

    @classmethod
    def smoothstep(cls, q0: np.ndarray, q1: np.ndarray, duration: float, dt: float = 0.01) -> JointMotion:
        """One rest-to-rest segment from q0 to q1 (7,) rad over ``duration`` s, smoothstep profile,
        sampled every ``dt`` s: a simple motion for fake arms, tests and benchmarks (no ruckig)."""
        q0, q1 = np.asarray(q0, np.float64), np.asarray(q1, np.float64)
        t = np.arange(0.0, duration + dt / 2, dt)
        s = t / duration
        a, da = 3 * s**2 - 2 * s**3, (6 * s - 6 * s**2) / duration
        return cls(
            times=t, q=q0 + a[:, None] * (q1 - q0), dq=da[:, None] * (q1 - q0),
            targets=q1[None], durations=np.array([duration]), limit_scale=np.array([1.0]),
        )

    @property
    def duration(self) -> float:
        """Total duration, s."""
        return float(self.times[-1]) if len(self.times) else 0.0

    @property
    def dt(self) -> float:
        """Sample step, s."""
        return float(self.times[1] - self.times[0]) if len(self.times) > 1 else 0.0

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Linearly interpolated (q, dq), each (7,), at time ``t`` s from motion start (clamped)."""
        if len(self.times) == 1 or t <= 0.0:
            return self.q[0].copy(), (self.dq[0].copy() if t > 0.0 else np.zeros(self.q.shape[1]))
        if t >= self.times[-1]:
            return self.q[-1].copy(), np.zeros(self.q.shape[1])
        x = t / self.dt
        i = min(int(x), len(self.times) - 2)
        a = x - i
        return (1 - a) * self.q[i] + a * self.q[i + 1], (1 - a) * self.dq[i] + a * self.dq[i + 1]
