"""A fake ``depthai`` module (2.x or 3.x flavour) that records the pipeline and serves RGB-D groups.

Nodes accept any configuration call and record it; ports link to each other. The device
serves ``MessageGroup``-like dicts {"color", "depth"} of ImgFrame-like messages at the size the
pipeline asked for, with device timestamps and sequence numbers; stalls and XLink errors can
be injected.
"""

from __future__ import annotations

import datetime
import types
from typing import Any

import numpy as np


class State:
    def __init__(self, version: str) -> None:
        self.version = version
        self.calls: list[tuple[str, str, tuple[Any, ...], dict[str, Any]]] = []  # (node, method, args, kwargs)
        self.links: list[tuple[str, str]] = []
        self.color_size: tuple[int, int] | None = None
        self.depth_size: tuple[int, int] | None = None  # None: same as colour
        self.devices: list[Any] = []
        self.opened = 0
        self.closed = 0
        self.stall_polls = 0
        self.link_error = 0
        self.seq = 0
        self.device_info: Any = None


STATE = State("2.30.0.0")


class _Port:
    def __init__(self, owner: str, name: str) -> None:
        self.label = f"{owner}.{name}"

    def link(self, other: _Port) -> None:
        STATE.links.append((self.label, other.label))

    def createOutputQueue(self, maxSize: int = 16, blocking: bool = True) -> _Queue:  # noqa: N802, N803
        assert STATE.version.startswith("3"), "createOutputQueue is depthai 3.x"
        STATE.calls.append((self.label, "createOutputQueue", (), {"maxSize": maxSize, "blocking": blocking}))
        return _Queue()


class _Inputs(dict):
    def __init__(self, owner: str) -> None:
        super().__init__()
        self.owner = owner

    def __missing__(self, key: str) -> _Port:
        port = _Port(self.owner, f"inputs[{key}]")
        self[key] = port
        return port


class _Node:
    PORTS = ("isp", "video", "out", "depth", "left", "right", "input", "disparity")

    def __init__(self, kind: str, index: int) -> None:
        self.kind = kind
        self.label = f"{kind}{index}"
        self.inputs = _Inputs(self.label)
        self.socket: Any = None

    def __getattr__(self, name: str) -> Any:
        if name in _Node.PORTS:
            port = _Port(self.label, name)
            object.__setattr__(self, name, port)
            return port
        if name.startswith("__"):
            raise AttributeError(name)

        def call(*args: Any, **kwargs: Any) -> Any:
            STATE.calls.append((self.label, name, args, kwargs))
            if name in ("build", "setBoardSocket"):
                self.socket = args[0] if args else kwargs.get("boardSocket")
                return self
            if name == "setIspScale":
                STATE.color_size = (1920 * args[0] // args[1], 1080 * args[0] // args[1])
            if name == "requestOutput":
                assert STATE.version.startswith("3")
                if self.socket == CameraBoardSocket.CAM_A:
                    STATE.color_size = tuple(args[0])
                return _Port(self.label, f"requestOutput{args[0]}")
            return None

        return call


class _NodeKind:
    def __init__(self, name: str) -> None:
        self.name = name


node = types.SimpleNamespace(
    ColorCamera=_NodeKind("ColorCamera"), MonoCamera=_NodeKind("MonoCamera"), Camera=_NodeKind("Camera"),
    StereoDepth=_NodeKind("StereoDepth"), Sync=_NodeKind("Sync"), XLinkOut=_NodeKind("XLinkOut"),
)
node.StereoDepth.PresetMode = types.SimpleNamespace(HIGH_DENSITY="HIGH_DENSITY", HIGH_ACCURACY="HIGH_ACCURACY")
CameraBoardSocket = types.SimpleNamespace(CAM_A="CAM_A", CAM_B="CAM_B", CAM_C="CAM_C")
ColorCameraProperties = types.SimpleNamespace(SensorResolution=types.SimpleNamespace(THE_1080_P="THE_1080_P"))
MonoCameraProperties = types.SimpleNamespace(SensorResolution=types.SimpleNamespace(THE_400_P="THE_400_P"))
ImgFrame = types.SimpleNamespace(Type=types.SimpleNamespace(RGB888i="RGB888i", NV12="NV12"))


class Pipeline:
    def __init__(self, device: Any = None) -> None:
        if STATE.version.startswith("3"):
            assert device is not None, "the driver passes its device to the 3.x Pipeline"
        self.nodes: list[_Node] = []
        self.started = False

    def create(self, kind: _NodeKind) -> _Node:
        n = _Node(kind.name, len(self.nodes))
        self.nodes.append(n)
        return n

    def start(self) -> None:
        assert STATE.version.startswith("3")
        self.started = True

    def stop(self) -> None:
        self.started = False


class DeviceInfo:
    def __init__(self, mxid: str) -> None:
        self.mxid = mxid


class CalibrationHandler:
    def getCameraIntrinsics(self, socket: str, w: int, h: int) -> list[list[float]]:  # noqa: N802
        assert socket == CameraBoardSocket.CAM_A
        return [[1.1 * w, 0.0, w / 2 + 1.5], [0.0, 1.1 * w, h / 2 - 2.5], [0.0, 0.0, 1.0]]


class _Img:
    def __init__(self, frame: np.ndarray, seq: int, stamp: float) -> None:
        self.frame, self.seq, self.stamp = frame, seq, stamp

    def getCvFrame(self) -> np.ndarray:  # noqa: N802
        return self.frame

    def getFrame(self) -> np.ndarray:  # noqa: N802
        return self.frame

    def getTimestampDevice(self) -> datetime.timedelta:  # noqa: N802
        return datetime.timedelta(seconds=self.stamp)

    def getSequenceNum(self) -> int:  # noqa: N802
        return self.seq


class _Queue:
    def tryGet(self) -> dict[str, _Img] | None:  # noqa: N802
        if STATE.link_error:
            STATE.link_error -= 1
            raise RuntimeError("Communication exception - possible device error/misconfiguration. Original "
                               "message 'Couldn't read data from stream: 'rgbd' (X_LINK_ERROR)'")
        if STATE.stall_polls:
            STATE.stall_polls -= 1
            return None
        STATE.seq += 1
        w, h = STATE.color_size
        dw, dh = STATE.depth_size or (w, h)
        bgr = np.zeros((h, w, 3), dtype=np.uint8)
        bgr[..., 0] = 200  # blue in BGR
        depth = np.full((dh, dw), 850, dtype=np.uint16)
        stamp = 100.0 + STATE.seq / 30.0
        return {"color": _Img(bgr, STATE.seq, stamp), "depth": _Img(depth, STATE.seq, stamp)}


class Device:
    def __init__(self, *args: Any) -> None:
        STATE.opened += 1
        STATE.devices.append(self)
        self.args = args
        if STATE.version.startswith("3"):
            assert not args or isinstance(args[0], DeviceInfo)
            STATE.device_info = args[0] if args else None
        else:
            assert isinstance(args[0], Pipeline)
            STATE.device_info = args[1] if len(args) > 1 else None

    def getOutputQueue(self, name: str, maxSize: int = 16, blocking: bool = True) -> _Queue:  # noqa: N802, N803
        assert STATE.version.startswith("2")
        STATE.calls.append(("device", "getOutputQueue", (name,), {"maxSize": maxSize, "blocking": blocking}))
        return _Queue()

    def readCalibration(self) -> CalibrationHandler:  # noqa: N802
        return CalibrationHandler()

    def close(self) -> None:
        STATE.closed += 1


def make_module(version: str = "2.30.0.0") -> types.ModuleType:
    """A fresh fake ``depthai`` module of the given version."""
    global STATE
    STATE = State(version)
    mod = types.ModuleType("depthai")
    mod.__version__ = version
    for name in ("node", "CameraBoardSocket", "ColorCameraProperties", "MonoCameraProperties", "ImgFrame",
                 "Pipeline", "DeviceInfo", "Device"):
        setattr(mod, name, globals()[name])
    mod.STATE = STATE
    return mod
