"""Luxonis OAK-D through depthai: colour camera + stereo depth aligned to colour.

Same RGBDCamera contract as the RealSense driver. The on-device pipeline is: colour camera
(CAM_A) at the configured size and rate, the two mono cameras (CAM_B/CAM_C) into a
``StereoDepth`` node with ``setDepthAlign(CAM_A)``, and a ``Sync`` node that pairs colour
and depth by timestamp into one ``MessageGroup``. Both depthai 2.x (``ColorCamera`` /
``MonoCamera`` / ``XLinkOut`` / ``Device(pipeline)``) and 3.x (``Camera.build`` /
``requestOutput`` / ``createOutputQueue`` / ``Pipeline(device).start()``) are supported.
Depth is uint16 millimetres (``depth_scale`` 0.001); intrinsics come from the device's
calibration for CAM_A at the output size; ``device_stamp`` is ``getTimestampDevice()``.
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import numpy as np

from drivers.base import DeviceError, DriverUnavailable
from drivers.clock import Clock, RealClock
from drivers.config import OakCameraConfig
from tdcommon.types import CameraIntrinsics, RGBDFrame

INSTALL_HINT = "pip install 'trackdeform3d[oak]'"
DEPTH_SCALE = 0.001  # depthai depth frames are millimetres
COLOR_SENSOR = (1920, 1080)  # the v2 ColorCamera runs THE_1080_P and scales the ISP output
POLL = 0.002  # s between queue polls

NOMINAL_HFOV_DEG = 69.0  # OAK-D CAM_A (IMX378), used only before connect()


def import_depthai() -> Any:
    """Import depthai or raise DriverUnavailable with the install command."""
    try:
        import depthai as dai  # lazy: only OAK stations need it
    except ImportError as exc:
        raise DriverUnavailable(f"the OAK driver needs depthai: {INSTALL_HINT}") from exc
    return dai


def depthai_major(dai: Any) -> int:
    """Major version of the imported depthai (2 or 3)."""
    try:
        return int(str(getattr(dai, "__version__", "2")).split(".")[0])
    except ValueError:
        return 2


def isp_scale(width: int, height: int) -> tuple[int, int]:
    """The v2 ISP scale (numerator, denominator) that turns 1920x1080 into ``width`` x ``height``."""
    f = Fraction(width, COLOR_SENSOR[0]).limit_denominator(63)
    if f > 1 or COLOR_SENSOR[0] * f != width or COLOR_SENSOR[1] * f != height:
        raise DeviceError(f"{width}x{height} is not an ISP scale of {COLOR_SENSOR[0]}x{COLOR_SENSOR[1]}",
                          recoverable=False)
    return f.numerator, f.denominator


class OakCamera:
    """An OAK-D colour + aligned stereo depth camera behind the RGBDCamera interface."""

    def __init__(self, config: OakCameraConfig, *, name: str | None = None, clock: Clock | None = None,
                 **_: Any) -> None:
        self.config = config
        self.id = config.id
        self.name = name or config.id
        self._clock: Clock = clock or RealClock()
        self._dai: Any = None
        self._device: Any = None
        self._pipeline: Any = None
        self._queue: Any = None
        self._intrinsics: CameraIntrinsics | None = None
        self.last_frame_number = -1
        self.dropped = 0

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Calibrated intrinsics of the colour image once connected; a nominal 69° HFOV pinhole before."""
        if self._intrinsics is None:
            return CameraIntrinsics.from_fov(self.config.width, self.config.height, NOMINAL_HFOV_DEG)
        return self._intrinsics

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        """Build and start the on-device pipeline, read the calibration, wait for a first frame."""
        dai = self._dai = import_depthai()
        try:
            if depthai_major(dai) >= 3:
                self._start_v3(dai)
            else:
                self._start_v2(dai)
            calib = self._device.readCalibration()
            k = np.asarray(calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, self.config.width,
                                                     self.config.height), dtype=np.float64)
        except RuntimeError as exc:
            if isinstance(exc, DeviceError):
                self.close()
                raise
            self.close()
            raise DeviceError(f"{self.name}: cannot start the OAK pipeline: {exc}") from exc
        self._intrinsics = CameraIntrinsics(self.config.width, self.config.height, float(k[0, 0]), float(k[1, 1]),
                                            float(k[0, 2]), float(k[1, 2]))
        try:
            self.read(timeout=self.config.start_timeout)  # the first frame proves the streams run
        except DeviceError:
            self.close()
            raise

    def _device_info(self, dai: Any) -> Any:
        return dai.DeviceInfo(self.config.device_id) if self.config.device_id else None

    def _stereo(self, dai: Any, pipeline: Any) -> Any:
        """The StereoDepth node, aligned to the colour camera."""
        stereo = pipeline.create(dai.node.StereoDepth)
        stereo.setDefaultProfilePreset(dai.node.StereoDepth.PresetMode.HIGH_DENSITY)
        stereo.setLeftRightCheck(True)
        stereo.setSubpixel(True)
        stereo.setDepthAlign(dai.CameraBoardSocket.CAM_A)
        return stereo

    def _start_v2(self, dai: Any) -> None:
        """depthai 2.x: ColorCamera ISP + MonoCameras -> StereoDepth -> Sync -> XLinkOut."""
        c = self.config
        num, den = isp_scale(c.width, c.height)
        pipeline = dai.Pipeline()
        color = pipeline.create(dai.node.ColorCamera)
        color.setBoardSocket(dai.CameraBoardSocket.CAM_A)
        color.setResolution(dai.ColorCameraProperties.SensorResolution.THE_1080_P)
        color.setIspScale(num, den)
        color.setFps(c.fps)
        stereo = self._stereo(dai, pipeline)
        for socket, port in ((dai.CameraBoardSocket.CAM_B, stereo.left), (dai.CameraBoardSocket.CAM_C, stereo.right)):
            mono = pipeline.create(dai.node.MonoCamera)
            mono.setBoardSocket(socket)
            mono.setResolution(dai.MonoCameraProperties.SensorResolution.THE_400_P)
            mono.setFps(c.fps)
            mono.out.link(port)
        sync = pipeline.create(dai.node.Sync)
        color.isp.link(sync.inputs["color"])
        stereo.depth.link(sync.inputs["depth"])
        xout = pipeline.create(dai.node.XLinkOut)
        xout.setStreamName("rgbd")
        sync.out.link(xout.input)
        info = self._device_info(dai)
        self._device = dai.Device(pipeline, info) if info is not None else dai.Device(pipeline)
        self._pipeline = pipeline
        self._queue = self._device.getOutputQueue(name="rgbd", maxSize=4, blocking=False)

    def _start_v3(self, dai: Any) -> None:
        """depthai 3.x: Camera nodes with requested outputs -> StereoDepth -> Sync -> host queue."""
        c = self.config
        info = self._device_info(dai)
        self._device = dai.Device(info) if info is not None else dai.Device()
        pipeline = dai.Pipeline(self._device)
        color = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
        color_out = color.requestOutput((c.width, c.height), dai.ImgFrame.Type.RGB888i, fps=c.fps,
                                        enableUndistortion=True)
        stereo = self._stereo(dai, pipeline)
        for socket, port in ((dai.CameraBoardSocket.CAM_B, stereo.left), (dai.CameraBoardSocket.CAM_C, stereo.right)):
            mono = pipeline.create(dai.node.Camera).build(socket)
            mono.requestOutput((640, 400), fps=c.fps).link(port)
        sync = pipeline.create(dai.node.Sync)
        color_out.link(sync.inputs["color"])
        stereo.depth.link(sync.inputs["depth"])
        self._queue = sync.out.createOutputQueue(maxSize=4, blocking=False)
        self._pipeline = pipeline
        pipeline.start()

    def close(self) -> None:
        """Stop the pipeline and release the device (idempotent)."""
        pipeline, device = self._pipeline, self._device
        self._pipeline = self._device = self._queue = None
        for obj, method in ((pipeline, "stop"), (device, "close")):
            if obj is not None and hasattr(obj, method):
                try:
                    getattr(obj, method)()
                except RuntimeError:
                    pass

    def recover(self) -> None:
        """Close and reopen the device (XLink errors leave the device unusable)."""
        self.close()
        self.connect()

    # ------------------------------------------------------------------ frames
    def read(self, timeout: float = 1.0) -> RGBDFrame:
        """The next synchronised colour + depth pair as an RGBDFrame."""
        if self._queue is None:
            raise DeviceError(f"{self.name}: not connected")
        deadline = self._clock.now() + timeout
        try:
            group = self._queue.tryGet()
            while group is None:
                if self._clock.now() >= deadline:
                    raise DeviceError(f"{self.name}: no frame within {timeout:.3f} s")
                self._clock.sleep_until(min(self._clock.now() + POLL, deadline))
                group = self._queue.tryGet()
            host_stamp = self._clock.now()
            color_msg, depth_msg = group["color"], group["depth"]
            color = np.ascontiguousarray(np.asarray(color_msg.getCvFrame(), dtype=np.uint8)[..., ::-1])  # BGR->RGB
            depth = np.array(depth_msg.getFrame(), dtype=np.uint16, copy=True)
            stamp = float(color_msg.getTimestampDevice().total_seconds())
            number = int(color_msg.getSequenceNum())
        except RuntimeError as exc:  # XLink errors surface as RuntimeError
            if isinstance(exc, DeviceError):
                raise
            raise DeviceError(f"{self.name}: device link failed: {exc}") from exc
        if color.shape[:2] != depth.shape or color.shape[:2] != (self.config.height, self.config.width):
            raise DeviceError(f"{self.name}: colour {color.shape[:2]} and depth {depth.shape} do not match the "
                              f"configured {self.config.height}x{self.config.width}", recoverable=False)
        if self.last_frame_number >= 0 and number > self.last_frame_number + 1:
            self.dropped += number - self.last_frame_number - 1
        self.last_frame_number = number
        return RGBDFrame(color, depth, DEPTH_SCALE, self.intrinsics, stamp, host_stamp, number)
