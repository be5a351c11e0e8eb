"""A fake ``depthai`` 3.x module that records the pipeline and serves RGB-D message groups.

Every class mirrors one real depthai class and offers only names that class has (checked by
tests/test_doubles_surface.py against the installed depthai): ``Pipeline(device)`` /
``create`` / ``start`` / ``stop``, ``node.Camera.build`` / ``requestOutput``,
``node.StereoDepth`` setters, ``node.Sync.inputs`` / ``out``, ``Node.Output.link`` /
``createOutputQueue(maxSize=16, blocking=False)``, ``MessageQueue.tryGet``, ``ImgFrame``
getters and ``ImgTransformation``. The queue serves ``{"color", "depth"}`` groups at the
size the pipeline asked for, with device timestamps and sequence numbers; stalls, XLink
errors and a closed queue can be injected.
"""

from __future__ import annotations

import datetime
import enum
import types
from typing import Any

import numpy as np

# Names the module offers that the real depthai does not: state and fault injection.
DOUBLE_ONLY = {"STATE", "State", "make_module", "DOUBLE_ONLY"}


class State:
    def __init__(self, version: str) -> None:
        self.version = version
        self.calls: list[tuple[str, str, tuple[Any, ...], dict[str, Any]]] = []  # (node, method, args, kwargs)
        self.links: list[tuple[str, str]] = []
        self.color_size: tuple[int, int] | None = None
        self.depth_size: tuple[int, int] | None = None  # set by StereoDepth.setOutputSize
        self.mono_size: tuple[int, int] = (640, 400)
        self.devices: list[Any] = []
        self.opened = 0
        self.closed = 0
        self.started = 0
        self.stall_polls = 0
        self.link_error = 0
        self.queue_closed = False
        self.with_transformation = True
        self.seq = 0
        self.device_info: Any = None


STATE = State("3.12.0")


class CameraBoardSocket(enum.Enum):
    CAM_A = 0
    CAM_B = 1
    CAM_C = 2


class ImgFrame:
    """depthai.ImgFrame: the getters the driver reads."""

    class Type(enum.Enum):
        RGB888i = 0
        BGR888i = 1
        NV12 = 2
        RAW16 = 3

    def __init__(self, frame: np.ndarray | None = None, seq: int = 0, stamp: float = 0.0,
                 transformation: ImgTransformation | None = None) -> None:
        self._frame, self._seq, self._stamp = frame, seq, stamp
        self._tr = transformation or ImgTransformation()

    def getCvFrame(self) -> np.ndarray:  # noqa: N802
        return self._frame

    def getFrame(self) -> np.ndarray:  # noqa: N802
        return self._frame

    def getTimestampDevice(self) -> datetime.timedelta:  # noqa: N802
        return datetime.timedelta(seconds=self._stamp)

    def getSequenceNum(self) -> int:  # noqa: N802
        return self._seq

    def getTransformation(self) -> ImgTransformation:  # noqa: N802
        return self._tr


class ImgTransformation:
    """depthai.ImgTransformation: size and total intrinsic matrix of a delivered image."""

    def __init__(self, width: int = 0, height: int = 0, k: list[list[float]] | None = None) -> None:
        self._size, self._k = (width, height), k

    def isValid(self) -> bool:  # noqa: N802
        return self._k is not None and self._size[0] > 0

    def getSize(self) -> tuple[int, int]:  # noqa: N802
        return self._size

    def getIntrinsicMatrix(self) -> list[list[float]]:  # noqa: N802
        return self._k if self._k is not None else [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]


class MessageQueue:
    """depthai.MessageQueue (host side): ``tryGet`` returns a group or None."""

    class QueueException(Exception):  # noqa: N818 - depthai's name
        """MessageQueue.QueueException (a closed queue)."""

    def tryGet(self) -> dict[str, ImgFrame] | None:  # noqa: N802
        if STATE.queue_closed:
            raise MessageQueue.QueueException("MessageQueue was closed")
        if STATE.link_error:
            STATE.link_error -= 1
            raise RuntimeError("Communication exception - possible device error/misconfiguration. Original "
                               "message 'Couldn't read data from stream: '__x_0_out' (X_LINK_ERROR)'")
        if STATE.stall_polls:
            STATE.stall_polls -= 1
            return None
        STATE.seq += 1
        w, h = STATE.color_size
        dw, dh = STATE.depth_size or STATE.mono_size
        bgr = np.zeros((h, w, 3), dtype=np.uint8)
        bgr[..., 0] = 200  # blue in BGR
        depth = np.full((dh, dw), 850, dtype=np.uint16)
        stamp = 100.0 + STATE.seq / 30.0
        k = [[1.2 * w, 0.0, w / 2 - 0.5], [0.0, 1.2 * w, h / 2 + 0.5], [0.0, 0.0, 1.0]]
        tr = ImgTransformation(w, h, k) if STATE.with_transformation else None
        return {"color": ImgFrame(bgr, STATE.seq, stamp, tr), "depth": ImgFrame(depth, STATE.seq, stamp)}


class Node:
    """depthai.Node: only its Output class is used."""

    class Output:
        DOUBLE_ONLY = {"label"}

        def __init__(self, label: str) -> None:
            self.label = label

        def link(self, other: Node.Input) -> None:
            STATE.links.append((self.label, other.label))

        def createOutputQueue(self, maxSize: int = 16, blocking: bool = False) -> MessageQueue:  # noqa: N802, N803
            STATE.calls.append((self.label, "createOutputQueue", (), {"maxSize": maxSize, "blocking": blocking}))
            return MessageQueue()

    class Input:
        DOUBLE_ONLY = {"label"}

        def __init__(self, label: str) -> None:
            self.label = label


class _Inputs(dict):
    def __init__(self, owner: str) -> None:
        super().__init__()
        self.owner = owner

    def __missing__(self, key: str) -> Node.Input:
        port = Node.Input(f"{self.owner}.inputs[{key}]")
        self[key] = port
        return port


class _DeviceNode:
    DOUBLE_ONLY = {"label", "record"}

    def __init__(self, label: str) -> None:
        self.label = label

    def record(self, method: str, *args: Any, **kwargs: Any) -> None:
        STATE.calls.append((self.label, method, args, kwargs))


class Camera(_DeviceNode):
    """depthai.node.Camera."""

    DOUBLE_ONLY = {"label", "record", "socket"}

    def __init__(self, label: str) -> None:
        super().__init__(label)
        self.socket: CameraBoardSocket | None = None

    def build(self, boardSocket: CameraBoardSocket, sensorResolution: Any = None,  # noqa: N803
              sensorFps: float | None = None) -> Camera:  # noqa: N803
        assert isinstance(boardSocket, CameraBoardSocket)
        self.record("build", boardSocket)
        self.socket = boardSocket
        return self

    def requestOutput(self, size: tuple[int, int], type: ImgFrame.Type | None = None,  # noqa: A002, N802
                      resizeMode: Any = None, fps: float | None = None,  # noqa: N803
                      enableUndistortion: bool | None = None) -> Node.Output:  # noqa: N803
        assert self.socket is not None, "build() before requestOutput()"
        assert type is None or isinstance(type, ImgFrame.Type)
        self.record("requestOutput", tuple(size), type=type, fps=fps, enableUndistortion=enableUndistortion)
        if self.socket == CameraBoardSocket.CAM_A:
            STATE.color_size = tuple(size)
        else:
            STATE.mono_size = tuple(size)
        return Node.Output(f"{self.label}.requestOutput{tuple(size)}")


class StereoDepth(_DeviceNode):
    """depthai.node.StereoDepth."""

    class PresetMode(enum.Enum):
        FAST_ACCURACY = 0
        FAST_DENSITY = 1
        DEFAULT = 2
        FACE = 3
        HIGH_DETAIL = 4
        ROBOTICS = 5

    DOUBLE_ONLY = {"label", "record"}

    def __init__(self, label: str) -> None:
        super().__init__(label)
        self.left = Node.Input(f"{label}.left")
        self.right = Node.Input(f"{label}.right")
        self.depth = Node.Output(f"{label}.depth")

    def setDefaultProfilePreset(self, mode: StereoDepth.PresetMode) -> None:  # noqa: N802
        assert isinstance(mode, StereoDepth.PresetMode)
        self.record("setDefaultProfilePreset", mode)

    def setLeftRightCheck(self, enable: bool) -> None:  # noqa: N802
        self.record("setLeftRightCheck", enable)

    def setSubpixel(self, enable: bool) -> None:  # noqa: N802
        self.record("setSubpixel", enable)

    def setDepthAlign(self, camera: CameraBoardSocket) -> None:  # noqa: N802
        self.record("setDepthAlign", camera)

    def setOutputSize(self, width: int, height: int) -> None:  # noqa: N802
        self.record("setOutputSize", width, height)
        STATE.depth_size = (width, height)


class Sync(_DeviceNode):
    """depthai.node.Sync."""

    DOUBLE_ONLY = {"label", "record"}

    def __init__(self, label: str) -> None:
        super().__init__(label)
        self.inputs = _Inputs(label)
        self.out = Node.Output(f"{label}.out")


node = types.SimpleNamespace(Camera=Camera, StereoDepth=StereoDepth, Sync=Sync)


class Pipeline:
    """depthai.Pipeline(defaultDevice)."""

    DOUBLE_ONLY = {"nodes", "started", "device"}

    def __init__(self, defaultDevice: Device) -> None:  # noqa: N803
        assert isinstance(defaultDevice, Device), "the driver passes its device to the Pipeline"
        self.device = defaultDevice
        self.nodes: list[Any] = []
        self.started = False

    def create(self, kind: type) -> Any:
        n = kind(f"{kind.__name__}{len(self.nodes)}")
        self.nodes.append(n)
        return n

    def start(self) -> None:
        STATE.started += 1
        self.started = True

    def stop(self) -> None:
        self.started = False


class DeviceInfo:
    """depthai.DeviceInfo(deviceIdOrName)."""

    def __init__(self, deviceIdOrName: str = "") -> None:  # noqa: N803
        self.deviceId = deviceIdOrName

    def getDeviceId(self) -> str:  # noqa: N802
        return self.deviceId


class CalibrationHandler:
    def getCameraIntrinsics(self, cameraId: CameraBoardSocket, resizeWidth: int = -1,  # noqa: N802, N803
                            resizeHeight: int = -1) -> list[list[float]]:  # noqa: N803
        assert cameraId == CameraBoardSocket.CAM_A
        w, h = resizeWidth, resizeHeight
        return [[1.1 * w, 0.0, w / 2 + 1.5], [0.0, 1.1 * w, h / 2 - 2.5], [0.0, 0.0, 1.0]]


class Device:
    """depthai.Device() / Device(deviceInfo)."""

    DOUBLE_ONLY = {"args"}

    def __init__(self, *args: Any) -> None:
        assert not args or isinstance(args[0], DeviceInfo)
        STATE.opened += 1
        STATE.devices.append(self)
        STATE.device_info = args[0] if args else None
        self.args = args

    def readCalibration(self) -> CalibrationHandler:  # noqa: N802
        return CalibrationHandler()

    def close(self) -> None:
        STATE.closed += 1


def make_module(version: str = "3.12.0") -> types.ModuleType:
    """A fresh fake ``depthai`` module of the given version."""
    global STATE
    STATE = State(version)
    mod = types.ModuleType("depthai")
    mod.__version__ = version
    for name in ("node", "Node", "CameraBoardSocket", "ImgFrame", "ImgTransformation", "MessageQueue", "Pipeline",
                 "DeviceInfo", "Device", "CalibrationHandler"):
        setattr(mod, name, globals()[name])
    mod.STATE = STATE
    return mod
