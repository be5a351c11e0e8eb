"""OakCamera's depthai 3 pipeline built against the real depthai classes, enums and messages.

Device nodes cannot be created without an OAK attached, so the pipeline the driver builds is
a checking stand-in: every node is the real ``dai.node`` class behind a proxy that lets
through only attributes the real class has, and checks each call against the real class's
pybind11 signatures (enum arguments must be the real enums). The messages the driver reads
are real ``ImgFrame`` / ``ImgTransformation`` / ``MessageGroup`` objects from a real host
``MessageQueue``; the calibration is a real ``CalibrationHandler``. Without hardware the real
``dai.Device()`` must fail as a DeviceError.
"""

from __future__ import annotations

import datetime
import types
from typing import Any

import numpy as np
import pytest

from drivers.base import DeviceError
from drivers.clock import SimClock
from drivers.config import OakCameraConfig
from drivers.oak import OakCamera
from tests.pybind_signatures import check_call

dai = pytest.importorskip("depthai", reason="depthai is not installed (pip install '.[oak]')")
pytestmark = pytest.mark.real_sdk

W, H = 640, 360
K_FRAME = [[520.0, 0.0, 321.0], [0.0, 521.0, 179.0], [0.0, 0.0, 1.0]]


class Record:
    """What the driver did to the checked pipeline."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str, tuple[Any, ...], dict[str, Any]]] = []
        self.links: list[tuple[str, str]] = []
        self.queue: Any = None
        self.started = 0
        self.closed = 0
        self.color_size: tuple[int, int] | None = None
        self.depth_size: tuple[int, int] | None = None
        self.mono_size: tuple[int, int] | None = None

    def called(self, method: str) -> list[tuple[tuple[Any, ...], dict[str, Any]]]:
        return [(a, k) for _, m, a, k in self.calls if m == method]


class Port:
    """A node's input/output; an output's methods are checked against the real dai.Node.Output."""

    def __init__(self, rec: Record, label: str, output: bool) -> None:
        self.rec, self.label, self.output = rec, label, output

    def link(self, other: Port) -> None:
        assert hasattr(dai.Node.Output, "link")
        assert self.output and not other.output, f"link {self.label} -> {other.label}: output to input only"
        self.rec.links.append((self.label, other.label))

    def createOutputQueue(self, *args: Any, **kwargs: Any) -> Any:  # noqa: N802
        assert self.output
        params = check_call(dai, dai.Node.Output.createOutputQueue, args, kwargs, "createOutputQueue")
        bound = dict(zip([p.name for p in params], args, strict=False)) | kwargs
        self.rec.calls.append((self.label, "createOutputQueue", args, kwargs))
        self.rec.queue = dai.MessageQueue("sync", bound.get("maxSize", 16), bound.get("blocking", False))
        return self.rec.queue


class InputMap(dict):
    def __init__(self, rec: Record, owner: str) -> None:
        super().__init__()
        self.rec, self.owner = rec, owner

    def __missing__(self, key: str) -> Port:
        port = Port(self.rec, f"{self.owner}.inputs[{key}]", output=False)
        self[key] = port
        return port


class CheckedNode:
    """A real node class behind a proxy: only its attributes, only calls its signatures accept."""

    def __init__(self, rec: Record, cls: type, label: str) -> None:
        self._rec, self._cls, self._label, self._socket = rec, cls, label, None
        self._ports: dict[str, Any] = {}

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        real = getattr(self._cls, name)  # AttributeError exactly where the real class has no such name
        if isinstance(real, property):  # a port: its getter's signature says Output, Input or InputMap
            if name not in self._ports:
                returns = (real.fget.__doc__ or "").rsplit("->", 1)[-1].strip()
                if returns.endswith("Node.InputMap"):
                    self._ports[name] = InputMap(self._rec, self._label)
                elif returns.endswith(("Node.Output", "Node.Input")):
                    self._ports[name] = Port(self._rec, f"{self._label}.{name}", returns.endswith("Output"))
                else:
                    raise AssertionError(f"{self._cls.__name__}.{name} is no port ({returns})")
            return self._ports[name]

        def call(*args: Any, **kwargs: Any) -> Any:
            params = check_call(dai, real, args, kwargs, name)
            bound = dict(zip([p.name for p in params], args, strict=False)) | kwargs
            self._rec.calls.append((self._label, name, args, kwargs))
            if name == "build":
                self._socket = bound.get("boardSocket")
                return self
            if name == "requestOutput":
                size = tuple(bound["size"])
                if self._socket == dai.CameraBoardSocket.CAM_A:
                    self._rec.color_size = size
                else:
                    self._rec.mono_size = size
                return Port(self._rec, f"{self._label}.requestOutput{size}", output=True)
            if name == "setOutputSize":
                self._rec.depth_size = (bound["width"], bound["height"])
            return None

        return call


def make_dai(rec: Record, groups: int = 3, with_transformation: bool = True) -> types.ModuleType:
    """The real depthai module with only Device and Pipeline replaced (no OAK attached)."""
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, [[1500.0, 0, 960], [0, 1500.0, 540], [0, 0, 1]],
                              1920, 1080)

    class Device:
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            check_call(dai, dai.Device.__init__, args, kwargs, "__init__")
            self.args = args

        def readCalibration(self) -> Any:  # noqa: N802
            assert hasattr(dai.Device, "readCalibration")
            return calib

        def close(self) -> None:
            assert hasattr(dai.Device, "close")
            rec.closed += 1

    class Pipeline:
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            check_call(dai, dai.Pipeline.__init__, args, kwargs, "__init__")
            assert args and isinstance(args[0], Device), "the driver builds the pipeline on its device"
            self.n = 0

        def create(self, cls: type) -> CheckedNode:
            assert hasattr(dai.Pipeline, "create") and cls in vars(dai.node).values(), cls
            self.n += 1
            return CheckedNode(rec, cls, f"{cls.__name__}{self.n}")

        def start(self) -> None:
            assert hasattr(dai.Pipeline, "start")
            rec.started += 1
            for seq in range(1, groups + 1):
                rec.queue.send(message_group(rec, seq, with_transformation))

        def stop(self) -> None:
            assert hasattr(dai.Pipeline, "stop")

    mod = types.ModuleType("depthai")
    for name in dir(dai):
        if not name.startswith("__"):
            setattr(mod, name, getattr(dai, name))
    mod.__version__ = dai.__version__
    mod.Device, mod.Pipeline = Device, Pipeline
    return mod


def message_group(rec: Record, seq: int, with_transformation: bool) -> Any:
    """A real MessageGroup of real ImgFrames as the device would send for the requested sizes."""
    w, h = rec.color_size
    dw, dh = rec.depth_size or rec.mono_size
    color = dai.ImgFrame()
    rgb = np.zeros((h, w, 3), np.uint8)
    rgb[..., 0] = 210  # red
    color.setCvFrame(np.ascontiguousarray(rgb[..., ::-1]), dai.ImgFrame.Type.RGB888i)  # setCvFrame takes BGR
    depth = dai.ImgFrame()
    depth.setFrame(np.full((dh, dw), 900 + seq, np.uint16))
    depth.setType(dai.ImgFrame.Type.RAW16)
    depth.setWidth(dw)
    depth.setHeight(dh)
    for f in (color, depth):
        f.setSequenceNum(seq)
        f.setTimestampDevice(datetime.timedelta(seconds=50.0 + seq / 30.0))
    if with_transformation:
        color.setTransformation(dai.ImgTransformation(w, h, K_FRAME))
    group = dai.MessageGroup()
    group["color"] = color
    group["depth"] = depth
    return group


def cam(**kw) -> OakCamera:
    return OakCamera(OakCameraConfig(id="oakd", width=W, height=H, fps=30.0, start_timeout=1.0, **kw),
                     clock=SimClock(2.0))


def test_v3_pipeline_against_the_real_node_classes_and_enums(monkeypatch):
    rec = Record()
    monkeypatch.setitem(__import__("sys").modules, "depthai", make_dai(rec))
    c = cam(device_id="1844301011A2B3C4D5")
    c.connect()
    (preset,), _ = rec.called("setDefaultProfilePreset")[0]
    assert isinstance(preset, dai.node.StereoDepth.PresetMode)
    assert rec.called("setDepthAlign")[0][0] == (dai.CameraBoardSocket.CAM_A,)
    assert rec.called("setOutputSize")[0][0] == (W, H)
    assert rec.color_size == (W, H) and rec.depth_size == (W, H)
    sockets = [a[0] for a, _ in rec.called("build")]
    assert sockets == [dai.CameraBoardSocket.CAM_A, dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C]
    assert {dst.split(".")[-1] for _, dst in rec.links} == {"left", "right", "inputs[color]", "inputs[depth]"}
    assert rec.queue.getBlocking() is False and rec.queue.getMaxSize() == 4
    k = c.intrinsics  # from the real ImgTransformation of the first colour frame
    assert (k.fx, k.fy, k.cx, k.cy) == (520.0, 521.0, 321.0, 179.0)
    f = c.read(timeout=0.5)
    assert f.color.shape == (H, W, 3) and f.color[0, 0].tolist() == [210, 0, 0]
    assert f.depth.shape == (H, W) and f.depth[0, 0] == 902
    assert f.device_stamp == pytest.approx(50.0 + 2 / 30) and f.frame_number == 2
    c.close()
    assert rec.closed == 1


def test_intrinsics_from_the_real_calibration_without_a_frame_transformation(monkeypatch):
    rec = Record()
    monkeypatch.setitem(__import__("sys").modules, "depthai", make_dai(rec, with_transformation=False))
    c = cam()
    c.connect()
    expected = dai.CalibrationHandler()
    expected.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, [[1500.0, 0, 960], [0, 1500.0, 540], [0, 0, 1]],
                                 1920, 1080)
    k_real = expected.getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, W, H)
    assert c.intrinsics.fx == pytest.approx(k_real[0][0]) and c.intrinsics.cx == pytest.approx(k_real[0][2])
    c.close()


def test_the_2x_preset_and_a_closed_queue_against_the_real_module(monkeypatch):
    assert not hasattr(dai.node.StereoDepth.PresetMode, "HIGH_DENSITY")  # why 2.x's preset name is gone
    rec = Record()
    monkeypatch.setitem(__import__("sys").modules, "depthai", make_dai(rec, groups=1))
    c = cam()
    c.connect()
    rec.queue.close()
    with pytest.raises(DeviceError, match="closed") as info:  # the real QueueException is no RuntimeError
        c.read(timeout=0.1)
    assert info.value.recoverable
    c.close()


def test_real_device_open_without_hardware_is_a_device_error(monkeypatch):
    monkeypatch.setenv("DEPTHAI_SEARCH_TIMEOUT", "300")  # ms; the default search waits 10 s
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK is attached: this test needs none")
    c = cam(device_id="1844301011A2B3C4D5")
    with pytest.raises(DeviceError, match="cannot start the OAK pipeline") as info:
        c.connect()
    assert info.value.recoverable
    c.close()
