"""A camera that plays recorded frames back: an episode ``.mcap``, a folder of them, or the paper's layout.

Frames are paced on the session clock at the configured ``fps`` (the real clock sleeps, the
simulated clock jumps), so a replay drives the daemon and the tracking worker exactly as a live
camera would. Frame numbers and device stamps are those recorded; when ``loop`` restarts the data
they are offset so they keep increasing (a device counter does not go back). ``host_stamp`` is the
clock at delivery. Every recorded frame is delivered: a late reader gets the next frame at once
and the 1/fps schedule restarts from there (no catch-up bursts, no drops).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from drivers.base import DeviceError
from drivers.clock import Clock, RealClock
from drivers.config import ReplayCameraConfig
from tdcommon.types import CameraIntrinsics, RGBDFrame

log = logging.getLogger(__name__)

NOMINAL_HFOV_DEG = 69.0  # intrinsics reported before connect when the file cannot be read


class ReplayCamera:
    """RGBDCamera playing ``config.path`` (via :func:`tdrecord.read_sequence`) at ``config.fps``."""

    def __init__(self, config: ReplayCameraConfig, *, clock: Clock | None = None, **context: Any) -> None:
        self.id = config.id
        self.config = config
        self.clock: Clock = clock if clock is not None else RealClock()
        self.path = Path(config.path).expanduser()
        self.sequence: Any = None  # tdrecord.Sequence once connected
        self.T_world_cam: np.ndarray | None = None  # (4, 4) the recording's camera pose, once known
        self.frames_delivered = 0
        self.loops = 0  # how many times the data restarted
        self._intrinsics: CameraIntrinsics | None = None
        self._iter: Iterator[RGBDFrame] | None = None
        self._pos = 0  # index of the next recorded frame the iterator yields
        self._pending: RGBDFrame | None = None  # next frame, already offset, not yet delivered
        self._next_due: float | None = None
        self._first: tuple[int, float] | None = None  # recorded (frame_number, device_stamp) of frame 0
        self._last: tuple[int, float] | None = None  # (frame_number, device_stamp) of the last frame read
        self._offset: tuple[int, float] = (0, 0.0)
        self._connected = False
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ Protocol
    @property
    def intrinsics(self) -> CameraIntrinsics:
        """The recording's intrinsics (read cheaply from its calibration); nominal ones if it cannot be read."""
        if self._intrinsics is None:
            from tdrecord import read_calibration

            try:
                cal = read_calibration(self.path)
            except (OSError, ValueError) as e:
                log.debug("camera %s: calibration of %s not readable yet (%s)", self.id, self.path, e)
                return CameraIntrinsics.from_fov(self.config.width, self.config.height, NOMINAL_HFOV_DEG)
            self._set_calibration(cal.K, cal.width, cal.height, cal.T_world_cam)
        assert self._intrinsics is not None
        return self._intrinsics

    def connect(self) -> None:
        """Read the recording's index (first connect) and continue where the last close() stopped."""
        from tdrecord import read_sequence

        with self._lock:
            if self.sequence is None:
                try:
                    seq = read_sequence(self.path)
                except (OSError, ValueError) as e:
                    raise DeviceError(f"camera {self.id}: cannot replay {self.path}: {e}", recoverable=False) from e
                if len(seq) == 0:
                    raise DeviceError(f"camera {self.id}: {self.path} holds no frames", recoverable=False)
                self.sequence = seq
                self._set_calibration(seq.K, seq.width, seq.height, seq.T_world_cam)
            if self._iter is None:
                self._iter = self._open(self._pos)
            self._next_due = None
            self._connected = True

    def close(self) -> None:
        """Stop streaming (idempotent); the position is kept for the next connect()."""
        with self._lock:
            self._connected = False
            if self._iter is not None:
                close = getattr(self._iter, "close", None)
                if close is not None:
                    close()
                self._iter = None

    def read(self, timeout: float = 1.0) -> RGBDFrame:
        """The next recorded frame at its 1/fps slot; DeviceError(recoverable=False) when the data ends."""
        with self._lock:
            if not self._connected:
                raise DeviceError(f"camera {self.id}: not connected", recoverable=True)
            if self._pending is None:
                self._pending = self._next_frame()
            now = self.clock.now()
            due = now if self._next_due is None else self._next_due
            if due - now > timeout:
                self.clock.sleep_until(now + timeout)
                raise DeviceError(f"camera {self.id}: no frame within {timeout} s", recoverable=True)
            self.clock.sleep_until(due)
            t = self.clock.now()
            frame = dataclasses.replace(self._pending, host_stamp=t)
            self._pending = None
            period = 1.0 / self.config.fps
            # on the 1/fps grid; a reader more than a period late restarts the grid at its delivery
            self._next_due = due + period if t < due + period else t + period
            self.frames_delivered += 1
            return frame

    # ------------------------------------------------------------------ internals
    def _set_calibration(self, K: np.ndarray, width: int, height: int, T_world_cam: np.ndarray) -> None:
        self._intrinsics = CameraIntrinsics.from_K(K, width, height)
        self.T_world_cam = np.asarray(T_world_cam, dtype=np.float64)
        if (width, height) != (self.config.width, self.config.height):
            log.warning(
                "camera %s: %s is %dx%d, the config says %dx%d; replaying the recorded size",
                self.id, self.path, width, height, self.config.width, self.config.height,
            )

    def _open(self, start: int) -> Iterator[RGBDFrame]:
        frames = self.sequence.frames
        if hasattr(frames, "iter_from"):
            return frames.iter_from(start)
        return iter(list(frames)[start:])

    def _next_frame(self) -> RGBDFrame:
        """The next recorded frame with loop offsets applied; restarts the data when looping."""
        assert self._iter is not None
        frame = next(self._iter, None)
        if frame is None and self.config.loop and self._last is not None:
            close = getattr(self._iter, "close", None)
            if close is not None:
                close()
            self._iter = self._open(0)
            self._pos = 0
            self.loops += 1
            assert self._first is not None
            fn0, t0 = self._first
            fn_last, t_last = self._last
            self._offset = (fn_last + 1 - fn0, t_last + 1.0 / self.config.fps - t0)
            frame = next(self._iter, None)
        if frame is None:
            raise DeviceError(
                f"camera {self.id}: replay finished ({self.path}: {self._pos} frames played"
                + (f", {self.loops} loops" if self.loops else "") + ")",
                recoverable=False,
            )
        if self._pos == 0 and self._first is None:
            self._first = (frame.frame_number, frame.device_stamp)
        self._pos += 1
        dn, dt = self._offset
        out = dataclasses.replace(frame, frame_number=frame.frame_number + dn, device_stamp=frame.device_stamp + dt)
        self._last = (out.frame_number, out.device_stamp)
        return out
