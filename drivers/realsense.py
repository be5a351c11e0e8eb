"""Intel RealSense D4xx through pyrealsense2: colour + depth, depth aligned to colour.

Streams RGB8 colour and Z16 depth at the configured size and rate, aligns every depth frame
to the colour camera with ``rs.align``, and reports the colour stream's intrinsics and the
depth sensor's ``depth_scale`` (metres per depth unit). ``device_stamp`` is the frame's
hardware timestamp (``frame_timestamp`` metadata, µs -> s, when the firmware provides it;
otherwise ``get_timestamp()`` ms -> s). The metadata is a 32-bit microsecond counter that
wraps every 2**32 µs (~71.6 min); it is unwrapped here so the stamps of an overnight
episode keep increasing. ``laser_power`` is rounded to the option's step and clamped to its
range as the device reports them (librealsense rejects an off-step value). pyrealsense2 is
imported lazily.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from drivers.base import DeviceError, DriverUnavailable
from drivers.clock import Clock, RealClock
from drivers.config import RealSenseCameraConfig
from tdcommon.types import CameraIntrinsics, RGBDFrame

INSTALL_HINT = "pip install 'trackdeform3d[realsense]' (and the system library libusb-1.0-0)"

NOMINAL_HFOV_DEG = 69.0  # D4xx colour camera, used only before connect()
STAMP_PERIOD_US = 1 << 32  # the frame_timestamp metadata counter wraps at 2**32 µs


class StampUnwrapper:
    """Unwraps a counter that wraps at ``period``: a step back by more than half a period is a wrap."""

    def __init__(self, period: int = STAMP_PERIOD_US) -> None:
        self.period = period
        self.wraps = 0
        self._last: int | None = None

    def __call__(self, raw: int) -> int:
        """The unwrapped value of ``raw`` (same unit), monotonic across wraps."""
        raw = int(raw) % self.period
        if self._last is not None and raw < self._last - self.period // 2:
            self.wraps += 1
        self._last = raw
        return raw + self.wraps * self.period


def snap_option(value: float, lo: float, hi: float, step: float) -> float:
    """``value`` clamped to [lo, hi] and rounded to the nearest ``lo + k * step``."""
    v = min(max(float(value), lo), hi)
    if step > 0:
        v = lo + round((v - lo) / step) * step
        if v > hi + 1e-9:
            v -= step
    return float(v)


def set_laser_power(rs: Any, sensor: Any, milliwatts: float) -> float | None:
    """Set the depth sensor's laser power to ``milliwatts`` on the option's own grid; the value set.

    Returns None when the sensor has no writable laser_power (e.g. a recording being played).
    """
    opt = rs.option.laser_power
    if not sensor.supports(opt) or sensor.is_option_read_only(opt):
        return None
    r = sensor.get_option_range(opt)
    value = snap_option(milliwatts, float(r.min), float(r.max), float(r.step))
    sensor.set_option(opt, value)
    return value


def import_rs() -> Any:
    """Import pyrealsense2 or raise DriverUnavailable with the install command."""
    try:
        import pyrealsense2 as rs  # lazy: only RealSense stations need it
    except ImportError as exc:
        raise DriverUnavailable(f"the RealSense driver needs pyrealsense2: {INSTALL_HINT}") from exc
    return rs


class RealSenseCamera:
    """A RealSense colour + depth camera behind the RGBDCamera interface."""

    def __init__(self, config: RealSenseCameraConfig, *, name: str | None = None, clock: Clock | None = None,
                 **_: Any) -> None:
        self.config = config
        self.id = config.id
        self.name = name or config.id
        self._clock: Clock = clock or RealClock()
        self._rs: Any = None
        self._pipeline: Any = None
        self._align: Any = None
        self._intrinsics: CameraIntrinsics | None = None
        self.depth_scale = 0.0
        self.serial: str | None = None
        self.last_frame_number = -1
        self.dropped = 0  # frames skipped by the device (frame-number gaps)
        self.laser_power: float | None = None  # mW actually set (on the option's step), None if untouched
        self._unwrap = StampUnwrapper()  # kept across reconnects: the device counter keeps running

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Calibrated intrinsics of the colour image once connected; a nominal 69° HFOV pinhole before."""
        if self._intrinsics is None:
            return CameraIntrinsics.from_fov(self.config.width, self.config.height, NOMINAL_HFOV_DEG)
        return self._intrinsics

    def connect(self) -> None:
        """Start colour + depth streaming and read intrinsics and depth scale."""
        rs = self._rs = import_rs()
        c = self.config
        fps = int(round(c.fps))
        try:
            cfg = rs.config()
            if c.serial:
                cfg.enable_device(c.serial)
            cfg.enable_stream(rs.stream.depth, c.width, c.height, rs.format.z16, fps)
            cfg.enable_stream(rs.stream.color, c.width, c.height, rs.format.rgb8, fps)
            self._pipeline = rs.pipeline()
            profile = self._pipeline.start(cfg)
        except RuntimeError as exc:
            self._pipeline = None
            raise DeviceError(f"{self.name}: cannot start streaming ({c.width}x{c.height}@{fps}): {exc}") from exc
        try:
            device = profile.get_device()
            self.serial = device.get_info(rs.camera_info.serial_number)
            depth_sensor = device.first_depth_sensor()
            self.depth_scale = float(depth_sensor.get_depth_scale())
            if c.laser_power is not None:
                self.laser_power = set_laser_power(rs, depth_sensor, c.laser_power)
            intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
            self._intrinsics = CameraIntrinsics(int(intr.width), int(intr.height), float(intr.fx), float(intr.fy),
                                                float(intr.ppx), float(intr.ppy))
            self._align = rs.align(rs.stream.color)
        except RuntimeError as exc:
            self.close()
            raise DeviceError(f"{self.name}: cannot configure the device: {exc}") from exc
        try:
            self.read(timeout=self.config.start_timeout)  # the first frame proves the streams run
        except DeviceError:
            self.close()
            raise

    def close(self) -> None:
        """Stop streaming (idempotent)."""
        pipeline, self._pipeline = self._pipeline, None
        if pipeline is not None:
            try:
                pipeline.stop()
            except RuntimeError:
                pass

    def read(self, timeout: float = 1.0) -> RGBDFrame:
        """Wait for the next frameset, align depth to colour and return it as an RGBDFrame."""
        if self._pipeline is None:
            raise DeviceError(f"{self.name}: not connected")
        try:
            frames = self._pipeline.wait_for_frames(int(max(timeout, 0.001) * 1000))
        except RuntimeError as exc:  # "Frame didn't arrive within <ms>"
            raise DeviceError(f"{self.name}: no frame within {timeout:.3f} s: {exc}") from exc
        host_stamp = self._clock.now()
        try:
            aligned = self._align.process(frames)
            color, depth = aligned.get_color_frame(), aligned.get_depth_frame()
            if not color or not depth:
                raise DeviceError(f"{self.name}: frameset without colour or depth")
            color_img = np.array(color.get_data(), dtype=np.uint8, copy=True)  # the SDK recycles buffers
            depth_img = np.array(depth.get_data(), dtype=np.uint16, copy=True)
            number = int(color.get_frame_number())
            stamp = self._device_stamp(color)
        except RuntimeError as exc:
            if isinstance(exc, DeviceError):
                raise
            raise DeviceError(f"{self.name}: bad frameset: {exc}") from exc
        if self.last_frame_number >= 0 and number > self.last_frame_number + 1:
            self.dropped += number - self.last_frame_number - 1
        self.last_frame_number = number
        return RGBDFrame(color_img, depth_img, self.depth_scale, self.intrinsics, stamp, host_stamp, number)

    def _device_stamp(self, frame: Any) -> float:
        """Hardware timestamp of ``frame`` in seconds (the 32-bit µs metadata counter unwrapped)."""
        meta = self._rs.frame_metadata_value.frame_timestamp
        if frame.supports_frame_metadata(meta):
            return float(self._unwrap(int(frame.get_frame_metadata(meta)))) * 1e-6
        return float(frame.get_timestamp()) * 1e-3

    def recover(self) -> None:
        """Restart the pipeline; reset the USB device first when a plain restart fails."""
        self.close()
        try:
            self.connect()
            return
        except DeviceError:
            pass
        rs = self._rs or import_rs()
        wanted = self.config.serial or self.serial
        reset = None
        try:
            for dev in rs.context().query_devices():
                serial = dev.get_info(rs.camera_info.serial_number)
                if wanted is None or serial == wanted:
                    dev.hardware_reset()
                    reset = serial
                    break
        except RuntimeError as exc:
            raise DeviceError(f"{self.name}: hardware reset failed: {exc}") from exc
        if reset is None:
            which = f"with serial {wanted}" if wanted else "at all"
            raise DeviceError(f"{self.name}: restart failed and no RealSense device {which} is connected; "
                              "check the USB cable, then retry recover()")
        raise DeviceError(f"{self.name}: device {reset} reset; it re-enumerates in a few seconds, retry recover()")
