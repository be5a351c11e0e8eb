"""Luxonis OAK-D through depthai 3.x: colour camera + stereo depth aligned to colour.

Same RGBDCamera contract as the RealSense driver. The on-device pipeline is: a ``Camera``
node on CAM_A with an output requested at the configured size and rate, two ``Camera``
nodes on CAM_B/CAM_C into a ``StereoDepth`` node with ``setDepthAlign(CAM_A)`` and
``setOutputSize`` pinned to the colour size, and a ``Sync`` node that pairs colour and
depth by timestamp into one ``MessageGroup`` read from a host queue
(``createOutputQueue``). Only depthai 3.x is supported (2.x has no ``Camera.build`` /
``requestOutput`` and needs ``XLinkOut``). Depth is uint16 millimetres (``depth_scale``
0.001); intrinsics come from the colour frame's ``ImgTransformation`` (the K of the image
as delivered, after scaling/cropping), or from the device calibration for CAM_A at the
output size when a frame carries none; ``device_stamp`` is ``getTimestampDevice()``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from drivers.base import DeviceError, DriverUnavailable
from drivers.clock import Clock, RealClock
from drivers.config import OakCameraConfig
from tdcommon.types import CameraIntrinsics, RGBDFrame

INSTALL_HINT = "pip install 'trackdeform3d[oak]'"
DEPTH_SCALE = 0.001  # depthai depth frames are millimetres
POLL = 0.002  # s between queue polls
MONO_SIZE = (640, 400)  # stereo input from the OV9282 mono pair (1280x800 binned 2x)
QUEUE_SIZE = 4
STEREO_PRESET = "DEFAULT"  # a PresetMode every 3.x release has (HIGH_DENSITY is 2.x only)

NOMINAL_HFOV_DEG = 69.0  # OAK-D CAM_A (IMX378), used only before connect()


def import_depthai() -> Any:
    """Import depthai 3.x or raise DriverUnavailable with the install command."""
    try:
        import depthai as dai  # lazy: only OAK stations need it
    except ImportError as exc:
        raise DriverUnavailable(f"the OAK driver needs depthai: {INSTALL_HINT}") from exc
    if depthai_major(dai) < 3:
        raise DriverUnavailable(f"the OAK driver needs depthai 3.x, found {getattr(dai, '__version__', '?')}: "
                                f"{INSTALL_HINT}")
    return dai


def depthai_major(dai: Any) -> int:
    """Major version of the imported depthai (0 when it cannot be read)."""
    try:
        return int(str(getattr(dai, "__version__", "0")).split(".")[0])
    except ValueError:
        return 0


def link_errors(dai: Any) -> tuple[type[BaseException], ...]:
    """Exceptions a lost device link raises: RuntimeError (XLink) and the host queue's QueueException."""
    queue_exc = getattr(getattr(dai, "MessageQueue", None), "QueueException", None)
    if isinstance(queue_exc, type) and issubclass(queue_exc, BaseException):
        return (RuntimeError, queue_exc)
    return (RuntimeError,)


def build_pipeline(dai: Any, pipeline: Any, config: OakCameraConfig) -> Any:
    """Add colour, mono pair, aligned stereo depth and Sync nodes to ``pipeline``; return Sync's output.

    The depth output is scaled to the colour size so the two images share pixels and K.
    """
    c = config
    color = pipeline.create(dai.node.Camera).build(dai.CameraBoardSocket.CAM_A)
    color_out = color.requestOutput((c.width, c.height), dai.ImgFrame.Type.RGB888i, fps=float(c.fps),
                                    enableUndistortion=True)
    stereo = pipeline.create(dai.node.StereoDepth)
    stereo.setDefaultProfilePreset(getattr(dai.node.StereoDepth.PresetMode, STEREO_PRESET))
    stereo.setLeftRightCheck(True)
    stereo.setSubpixel(True)
    stereo.setDepthAlign(dai.CameraBoardSocket.CAM_A)
    stereo.setOutputSize(c.width, c.height)
    for socket, port in ((dai.CameraBoardSocket.CAM_B, stereo.left), (dai.CameraBoardSocket.CAM_C, stereo.right)):
        mono = pipeline.create(dai.node.Camera).build(socket)
        mono.requestOutput(MONO_SIZE, fps=float(c.fps)).link(port)
    sync = pipeline.create(dai.node.Sync)
    color_out.link(sync.inputs["color"])
    stereo.depth.link(sync.inputs["depth"])
    return sync.out


def frame_intrinsics(msg: Any, width: int, height: int) -> CameraIntrinsics | None:
    """K of an ImgFrame from its ImgTransformation, or None when it has no valid one of that size."""
    getter = getattr(msg, "getTransformation", None)
    if getter is None:
        return None
    tr = getter()
    if tr is None or not tr.isValid() or tuple(tr.getSize()) != (width, height):
        return None
    k = np.asarray(tr.getIntrinsicMatrix(), dtype=np.float64)
    return CameraIntrinsics(width, height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))


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
        self._errors: tuple[type[BaseException], ...] = (RuntimeError,)
        self._intrinsics: CameraIntrinsics | None = None
        self._k_from_frame = False
        self.last_frame_number = -1
        self.dropped = 0

    @property
    def intrinsics(self) -> CameraIntrinsics:
        """Intrinsics of the colour image once connected; a nominal 69° HFOV pinhole before."""
        if self._intrinsics is None:
            return CameraIntrinsics.from_fov(self.config.width, self.config.height, NOMINAL_HFOV_DEG)
        return self._intrinsics

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        """Open the device, build and start the pipeline, read the calibration, wait for a first frame.

        Any failure closes what was opened; an API mismatch (AttributeError/TypeError from a
        depthai build the driver does not match) is a non-recoverable DeviceError.
        """
        dai = self._dai = import_depthai()
        self._errors = link_errors(dai)
        c = self.config
        try:
            info = dai.DeviceInfo(c.device_id) if c.device_id else None
            self._device = dai.Device(info) if info is not None else dai.Device()
            self._pipeline = dai.Pipeline(self._device)
            out = build_pipeline(dai, self._pipeline, c)
            self._queue = out.createOutputQueue(maxSize=QUEUE_SIZE, blocking=False)
            calib = self._device.readCalibration()
            k = np.asarray(calib.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, c.width, c.height),
                           dtype=np.float64)
            self._intrinsics = CameraIntrinsics(c.width, c.height, float(k[0, 0]), float(k[1, 1]),
                                                float(k[0, 2]), float(k[1, 2]))
            self._k_from_frame = False
            self._pipeline.start()
        except DeviceError:
            self.close()
            raise
        except (AttributeError, TypeError) as exc:
            self.close()
            raise DeviceError(f"{self.name}: depthai {getattr(dai, '__version__', '?')} does not match the OAK "
                              f"driver: {exc}", recoverable=False) from exc
        except self._errors as exc:
            self.close()
            raise DeviceError(f"{self.name}: cannot start the OAK pipeline: {exc}") from exc
        except BaseException:
            self.close()
            raise
        try:
            self.read(timeout=c.start_timeout)  # the first frame proves the streams run
        except DeviceError:
            self.close()
            raise

    def close(self) -> None:
        """Stop the pipeline and release the device (idempotent)."""
        pipeline, device = self._pipeline, self._device
        self._pipeline = self._device = self._queue = None
        for obj, method in ((pipeline, "stop"), (device, "close")):
            if obj is not None and hasattr(obj, method):
                try:
                    getattr(obj, method)()
                except self._errors:
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
            k = None if self._k_from_frame else frame_intrinsics(color_msg, self.config.width, self.config.height)
        except DeviceError:
            raise
        except self._errors as exc:  # XLink errors and a closed queue
            raise DeviceError(f"{self.name}: device link failed: {exc}") from exc
        if color.shape[:2] != depth.shape or color.shape[:2] != (self.config.height, self.config.width):
            raise DeviceError(f"{self.name}: colour {color.shape[:2]} and depth {depth.shape} do not match the "
                              f"configured {self.config.height}x{self.config.width}", recoverable=False)
        if k is not None:
            self._intrinsics, self._k_from_frame = k, True
        if self.last_frame_number >= 0 and number > self.last_frame_number + 1:
            self.dropped += number - self.last_frame_number - 1
        self.last_frame_number = number
        return RGBDFrame(color, depth, DEPTH_SCALE, self.intrinsics, stamp, host_stamp, number)
