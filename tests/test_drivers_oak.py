"""OakCamera against a fake ``depthai`` (2.x and 3.x flavours; no camera, no SDK)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from drivers.base import DeviceError, DriverUnavailable, create_camera
from drivers.clock import SimClock
from drivers.config import OakCameraConfig
from drivers.oak import OakCamera, isp_scale
from tests.doubles import fake_depthai


@pytest.fixture(params=["2.30.0.0", "3.0.0"])
def dai(request, monkeypatch):
    mod = fake_depthai.make_module(request.param)
    monkeypatch.setitem(sys.modules, "depthai", mod)
    return mod


def cam(**kw) -> OakCamera:
    kw.setdefault("width", 1280)
    kw.setdefault("height", 720)
    return create_camera(OakCameraConfig(id="oakd", **kw), clock=SimClock(3.0))


def test_pipeline_aligns_stereo_depth_to_colour(dai):
    c = cam(device_id="18443010D1A2B3C4")
    c.connect()
    calls = {(m, a) for _, m, a, _ in dai.STATE.calls}
    assert ("setDepthAlign", ("CAM_A",)) in calls
    assert any(src.endswith(".depth") and dst.endswith("inputs[depth]") for src, dst in dai.STATE.links)
    assert any(dst.endswith(".left") for _, dst in dai.STATE.links)
    assert any(dst.endswith(".right") for _, dst in dai.STATE.links)
    assert dai.STATE.device_info.mxid == "18443010D1A2B3C4"
    if dai.__version__.startswith("2"):
        assert ("setIspScale", (2, 3)) in calls
    else:
        assert any(m == "requestOutput" and a[0] == (1280, 720) for _, m, a, _ in dai.STATE.calls)
    k = c.intrinsics
    assert (k.width, k.height, k.fx, k.cx, k.cy) == (1280, 720, pytest.approx(1408.0), 641.5, 357.5)
    c.close()
    c.close()


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


def test_frame_timeout_and_link_error_then_recover(dai):
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
    c.recover()
    assert dai.STATE.opened == 2 and dai.STATE.closed == 1
    assert c.read().color.shape == (720, 1280, 3)


def test_mismatched_depth_size_is_reported(dai):
    c = cam()
    dai.STATE.depth_size = (640, 400)
    with pytest.raises(DeviceError, match="do not match"):
        c.connect()
    assert dai.STATE.closed == 1  # a failed connect releases the device


def test_isp_scale():
    assert isp_scale(1280, 720) == (2, 3)
    assert isp_scale(1920, 1080) == (1, 1)
    assert isp_scale(640, 360) == (1, 3)
    with pytest.raises(DeviceError):
        isp_scale(1280, 800)


def test_missing_depthai_raises_driver_unavailable(monkeypatch):
    monkeypatch.setitem(sys.modules, "depthai", None)
    with pytest.raises(DriverUnavailable, match=r"pip install 'trackdeform3d\[oak\]'"):
        cam().connect()
