"""Camera–arm time sync: each frame paired with both arms' joint states at its capture time, on the host clock.

A camera stamps a frame on its own clock (``device_stamp``); the host receives it ``latency`` later
(exposure, transfer, driver queue) and stamps ``host_stamp``; joint states are stamped on the host
clock. For frame i::

    host_i - device_i = (host clock - device clock)(t_i) + latency + jitter_i,   jitter_i >= 0

so the lower envelope of ``host - device`` is the clock offset plus the fixed latency. The
:class:`ClockOffsetEstimator` tracks that envelope online (the minimum per 1 s block of device time,
a least-squares line through the block minima of the last ``offset_window_s``: offset and drift);
the fixed part of the latency cannot be told from the offset by timestamps alone, so it is
configured (``sync.camera_latency_s``, measured once per camera). The capture time of a frame on
the host clock is then ``device + envelope(device) - camera_latency_s``, and :class:`TimeSync`
interpolates each arm's joints (linear, per joint) and gripper width at that time from the recent
joint states; ``grasped`` is the last sample's at or before it; u_t (12,) is the TCP pose of the
interpolated joints (forward kinematics). The pairing error of a frame is the time from its capture
time to the nearest joint-state sample actually used (0 when it falls on one, the time since the
newest one when it lies beyond every sample so far). Frames are recorded unpaired when no sample
is within ``max_pairing_gap_s``.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

ARMS = ("left", "right")
BLOCK_S = 1.0  # device-time length of one block of the lower envelope, s
RESET_S = 5.0  # a jump of host - device by more than this is a clock reset (a reconnected camera)


class ClockOffsetEstimator:
    """Online lower envelope of ``host - device`` (s) against device time: offset + fixed latency, with drift."""

    def __init__(self, window_s: float = 30.0) -> None:
        self.window_s = window_s
        self._blocks: deque[tuple[float, float]] = deque()  # (device time of the block minimum, minimum)
        self._block_start: float | None = None
        self._cur: tuple[float, float] | None = None
        self._fit: tuple[float, float, float] | None = None  # (x_ref, a, b): envelope(x) = a + b (x - x_ref)
        self.resets = 0

    def add(self, device: float, host: float) -> None:
        """Take one frame's stamps (s); the envelope is refitted only when one of its points changed."""
        y = host - device
        if self._fit is not None and abs(y - self.envelope(device)) > RESET_S:
            self.reset()
            self.resets += 1
        if self._block_start is None or device - self._block_start >= BLOCK_S or device < self._block_start:
            if self._cur is not None:
                self._blocks.append(self._cur)
            self._block_start, self._cur = device, (device, y)
            while self._blocks and device - self._blocks[0][0] > self.window_s:
                self._blocks.popleft()
        elif y < self._cur[1]:
            self._cur = (device, y)
        else:
            return
        self._refit()

    def reset(self) -> None:
        """Forget every sample (the device clock jumped)."""
        self._blocks.clear()
        self._block_start = self._cur = self._fit = None

    def _refit(self) -> None:
        assert self._cur is not None
        pts = np.array([*self._blocks, self._cur], dtype=np.float64)  # (B, 2)
        x_ref = float(pts[-1, 0])
        if len(pts) < 3 or pts[-1, 0] - pts[0, 0] < 2 * BLOCK_S:
            self._fit = (x_ref, float(pts[:, 1].min()), 0.0)
            return
        x, y = pts[:, 0] - x_ref, pts[:, 1]
        dx = x - x.mean()
        b = float(dx @ (y - y.mean()) / (dx @ dx))  # least-squares line (what polyfit(x, y, 1) gives, cheaper)
        a = float(y.mean() - b * x.mean())
        # the line must stay under every block minimum (an envelope): shift it down to the lowest residual
        a += min(0.0, float(np.min(pts[:, 1] - (a + b * x))))
        self._fit = (x_ref, float(a), float(b))

    @property
    def ready(self) -> bool:
        """True once a frame has been added."""
        return self._fit is not None

    def envelope(self, device: float) -> float:
        """Estimated ``host - device`` lower envelope at device time ``device``, s."""
        if self._fit is None:
            raise RuntimeError("no frame stamps yet")
        x_ref, a, b = self._fit
        return a + b * (device - x_ref)

    @property
    def drift_ppm(self) -> float:
        """Device clock rate relative to the host's, parts per million (positive: the device clock runs fast)."""
        return 0.0 if self._fit is None else -self._fit[2] * 1e6


class StateHistory:
    """The recent joint-state samples of both arms (a ring of ``capacity``), for interpolation at any time.

    A row is [q_left (7), q_right (7), width_left, width_right, grasped_left, grasped_right]; stamps in s, host.
    """

    WIDTH = 18

    def __init__(self, capacity: int = 1024) -> None:
        self._t = np.full(capacity, np.nan)
        self._v = np.zeros((capacity, self.WIDTH))
        self._n = 0
        self._lock = threading.Lock()

    def add(self, msg: dict[str, Any]) -> None:
        """Take one ``arms/state`` message (see tdcommon.wire)."""
        row = np.empty(self.WIDTH)
        row[:7], row[7:14] = msg["left"]["q"], msg["right"]["q"]
        row[14], row[15] = float(msg["left"]["gripper_width"]), float(msg["right"]["gripper_width"])
        row[16], row[17] = float(bool(msg["left"]["grasped"])), float(bool(msg["right"]["grasped"]))
        with self._lock:
            i = self._n % len(self._t)
            self._t[i], self._v[i] = float(msg["stamp"]), row
            self._n += 1

    def _ordered(self) -> tuple[np.ndarray, np.ndarray]:
        with self._lock:
            n, cap = self._n, len(self._t)
            if n <= cap:
                return self._t[:n].copy(), self._v[:n].copy()
            i = n % cap
            return np.concatenate([self._t[i:], self._t[:i]]), np.concatenate([self._v[i:], self._v[:i]])

    def at(self, t: float) -> tuple[np.ndarray, float] | None:
        """(row (18,) at time ``t``, s to the nearest sample used), or None without samples.

        Joints and widths are interpolated between the samples around ``t`` (held beyond the ends),
        the grasp flags are the last sample's at or before ``t``.
        """
        ts, vs = self._ordered()
        if len(ts) == 0:
            return None
        j = int(np.searchsorted(ts, t, side="right"))  # ts[j-1] <= t < ts[j]
        if j == 0:
            return vs[0].copy(), float(ts[0] - t)
        if j == len(ts):
            return vs[-1].copy(), float(t - ts[-1])
        t0, t1 = ts[j - 1], ts[j]
        w = 0.0 if t1 <= t0 else (t - t0) / (t1 - t0)
        row = vs[j - 1] + w * (vs[j] - vs[j - 1])
        row[16:] = vs[j - 1, 16:]
        return row, float(min(t - t0, t1 - t))


class TimeSync:
    """Pairs frames with the joint states at their capture time and keeps per-episode figures.

    ``tcp_pose(arm, q)`` gives an arm's TCP pose (4, 4) in the world for joints q (7,): u_t comes from it.
    """

    def __init__(self, latency_s: float, tcp_input: Callable[[str, np.ndarray], np.ndarray],
                 window_s: float = 30.0, max_gap_s: float = 0.05) -> None:
        self.latency_s = latency_s
        self.max_gap_s = max_gap_s
        self.tcp_input = tcp_input  # (arm, q (7,)) -> u of that arm (6,): TCP xyz m + rotation vector rad, world
        self.offset = ClockOffsetEstimator(window_s)
        self.states = StateHistory()
        self.reset_episode()

    def reset_episode(self) -> None:
        """Start the per-episode figures afresh."""
        self._errors: list[float] = []
        self._delays: list[float] = []
        self._unpaired = 0

    def capture_time(self, device_stamp: float, host_stamp: float) -> float:
        """The frame's capture time on the host clock, s (after taking its stamps into the offset estimate)."""
        self.offset.add(device_stamp, host_stamp)
        return device_stamp + self.offset.envelope(device_stamp) - self.latency_s

    def pair(self, frame_number: int, device_stamp: float, host_stamp: float) -> dict[str, Any] | None:
        """The joint state at the frame's capture time as an ``arms/state``-like message, or None (unpaired).

        ``{"frame_number", "stamp" (capture time, host clock s), "left": {"q", "gripper_width", "grasped"},
        "right": {...}, "u": [12], "pairing_error_s", "device_minus_host_s"}``
        """
        t = self.capture_time(device_stamp, host_stamp)
        self._delays.append(host_stamp - t)
        got = self.states.at(t)
        if got is None or got[1] > self.max_gap_s:
            self._unpaired += 1
            return None
        row, err = got
        self._errors.append(err)
        msg: dict[str, Any] = {"frame_number": int(frame_number), "stamp": t}
        u = []
        for k, arm in enumerate(ARMS):
            q = row[7 * k : 7 * k + 7]
            msg[arm] = {"q": q.tolist(), "gripper_width": float(row[14 + k]), "grasped": bool(row[16 + k] > 0.5)}
            u.append(self.tcp_input(arm, q))
        msg["u"] = np.concatenate(u).tolist()
        msg["pairing_error_s"] = err
        msg["device_minus_host_s"] = self.device_minus_host(device_stamp)
        return msg

    def device_minus_host(self, device_stamp: float) -> float:
        """Estimated device clock minus host clock at ``device_stamp``, s (the configured latency taken out)."""
        return -(self.offset.envelope(device_stamp) - self.latency_s)

    def episode_report(self, device_stamp: float | None) -> dict[str, Any]:
        """What one episode's metadata says about its time sync (errors and delays in s)."""
        errs, delays = np.asarray(self._errors), np.asarray(self._delays)
        rep: dict[str, Any] = {
            "method": "capture time = device stamp + online clock offset - latency; joints interpolated there",
            "latency_s": self.latency_s,
            "frames_paired": int(len(errs)),
            "frames_unpaired": int(self._unpaired),
            "pairing_error_s": {"mean": float(errs.mean()), "max": float(errs.max())} if len(errs) else None,
            "arrival_delay_s": {"mean": float(delays.mean()), "max": float(delays.max())} if len(delays) else None,
            "clock_drift_ppm": self.offset.drift_ppm,
            "device_minus_host_s": None,
        }
        if device_stamp is not None and self.offset.ready:
            rep["device_minus_host_s"] = self.device_minus_host(device_stamp)
        return rep
