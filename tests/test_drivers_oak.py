"""OakCamera against a fake ``depthai`` 3.x (no camera, no SDK)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from drivers.base import DeviceError, DriverUnavailable, create_camera
from drivers.clock import SimClock
from drivers.config import OakCameraConfig
from drivers.oak import OakCamera
from tests.doubles import fake_depthai


@pytest.fixture
def dai(monkeypatch):
    mod = fake_depthai.make_module()
    monkeypatch.setitem(sys.modules, "depthai", mod)
    return mod


def cam(**kw) -> OakCamera:
    kw.setdefault("width", 1280)
    kw.setdefault("height", 720)
    return create_camera(OakCameraConfig(id="oakd", **kw), clock=SimClock(3.0))


def test_pipeline_aligns_stereo_depth_to_colour_at_the_colour_size(dai):
    c = cam(device_id="18443010D1A2B3C4")
    c.connect()
    calls = {(m, a) for _, m, a, _ in dai.STATE.calls}
    assert ("setDepthAlign", (dai.CameraBoardSocket.CAM_A,)) in calls
    assert ("setOutputSize", (1280, 720)) in calls
    assert ("setDefaultProfilePreset", (dai.node.StereoDepth.PresetMode.DEFAULT,)) in calls
    assert any(src.endswith(".depth") and dst.endswith("inputs[depth]") for src, dst in dai.STATE.links)
    assert any(dst.endswith(".left") for _, dst in dai.STATE.links)
    assert any(dst.endswith(".right") for _, dst in dai.STATE.links)
    assert dai.STATE.device_info.getDeviceId() == "18443010D1A2B3C4"
    assert any(m == "requestOutput" and a[0] == (1280, 720) for _, m, a, _ in dai.STATE.calls)
    queue = [kw for _, m, _, kw in dai.STATE.calls if m == "createOutputQueue"]
    assert queue == [{"maxSize": 4, "blocking": False}]
    assert dai.STATE.started == 1
    k = c.intrinsics  # from the first frame's ImgTransformation
    assert (k.width, k.height, k.fx, k.cx, k.cy) == (1280, 720, pytest.approx(1536.0), 639.5, 360.5)
    c.close()
    c.close()
    assert dai.STATE.closed == 1


def test_intrinsics_fall_back_to_the_calibration_without_a_transformation(dai):
    dai.STATE.with_transformation = False
    c = cam()
    c.connect()
    k = c.intrinsics
    assert (k.fx, k.cx, k.cy) == (pytest.approx(1408.0), 641.5, 357.5)


def test_read_returns_rgb_frame_with_depth_in_mm(dai):
    c = cam()
    c.connect()
    f = c.read(timeout=0.5)
    assert f.color.shape == (720, 1280, 3) and f.color.dtype == np.uint8
    assert f.color[0, 0].tolist() == [0, 0, 200]  # BGR from the device, RGB out
    assert f.depth.shape == (720, 1280) and f.depth.dtype == np.uint16
    assert f.depth_scale == 0.001 and f.depth_m()[5, 5] == pytest.approx(0.85)
    assert f.frame_number == 2 and f.device_stamp == pytest.approx(100.0 + 2 / 30)
    assert f.host_stamp == pytest.approx(3.0)


def test_frame_timeout_link_error_and_closed_queue_then_recover(dai):
    c = cam()
    c.connect()
    dai.STATE.stall_polls = 10_000
    with pytest.raises(DeviceError, match="no frame within") as info:
        c.read(timeout=0.1)
    assert info.value.recoverable
    dai.STATE.stall_polls = 0
    dai.STATE.link_error = 1
    with pytest.raises(DeviceError, match="X_LINK_ERROR"):
        c.read()
    dai.STATE.queue_closed = True
    with pytest.raises(DeviceError, match="closed") as info:
        c.read()
    assert info.value.recoverable
    dai.STATE.queue_closed = False
    c.recover()
    assert dai.STATE.opened == 2 and dai.STATE.closed == 1
    assert c.read().color.shape == (720, 1280, 3)


def test_mismatched_depth_size_is_reported_and_the_device_closed(dai, monkeypatch):
    monkeypatch.setattr(fake_depthai.StereoDepth, "setOutputSize", lambda self, w, h: None)
    with pytest.raises(DeviceError, match="do not match"):
        cam().connect()
    assert dai.STATE.closed == 1  # a failed connect releases the device


def test_api_mismatch_is_a_non_recoverable_device_error_and_closes_the_device(dai, monkeypatch):
    monkeypatch.delattr(fake_depthai.StereoDepth, "setOutputSize")
    with pytest.raises(DeviceError, match="does not match the OAK driver") as info:
        cam().connect()
    assert not info.value.recoverable
    assert dai.STATE.opened == 1 and dai.STATE.closed == 1


def test_depthai_2_is_refused_with_the_install_command(dai):
    dai.__version__ = "2.30.0.0"
    with pytest.raises(DriverUnavailable, match=r"needs depthai 3\.x.*trackdeform3d\[oak\]"):
        cam().connect()


def test_missing_depthai_raises_driver_unavailable(monkeypatch):
    monkeypatch.setitem(sys.modules, "depthai", None)
    with pytest.raises(DriverUnavailable, match=r"pip install 'trackdeform3d\[oak\]'"):
        cam().connect()
