"""RealSenseCamera against a fake ``pyrealsense2`` (no camera, no SDK)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from drivers.base import DeviceError, DriverUnavailable, create_camera
from drivers.clock import SimClock
from drivers.config import RealSenseCameraConfig
from drivers.realsense import RealSenseCamera
from tests.doubles import fake_realsense


@pytest.fixture
def rs(monkeypatch):
    mod = fake_realsense.make_module()
    monkeypatch.setitem(sys.modules, "pyrealsense2", mod)
    return mod


def cam(**kw) -> RealSenseCamera:
    return create_camera(RealSenseCameraConfig(id="d455", width=640, height=360, fps=30, **kw), clock=SimClock(5.0))


def test_connect_configures_streams_and_reads_calibration(rs):
    c = cam(serial="123456789012", laser_power=160.0)
    c.connect()
    assert ("color", 640, 360, "rgb8", 30) in rs.STATE.enabled
    assert ("depth", 640, 360, "z16", 30) in rs.STATE.enabled
    assert rs.STATE.options["laser_power"] == 150.0 == c.laser_power  # on the option's 30 mW step
    assert c.depth_scale == 0.001 and c.serial == "123456789012"
    k = c.intrinsics
    assert (k.width, k.height, k.fx, k.cx, k.cy) == (640, 360, 576.0, 319.7, 180.7)
    c.close()
    c.close()
    assert rs.STATE.stops == 1


def test_read_returns_aligned_rgbd_frame_with_hardware_stamp(rs):
    c = cam()
    c.connect()
    f = c.read(timeout=0.5)
    assert f.color.shape == (360, 640, 3) and f.color.dtype == np.uint8
    assert f.depth.shape == (360, 640) and f.depth.dtype == np.uint16
    assert f.depth_scale == 0.001 and f.intrinsics == c.intrinsics
    assert rs.STATE.timeouts[-1] == 500
    assert f.frame_number == 2  # the first frame was read by connect()
    assert f.device_stamp == pytest.approx(1.0 + 2 / 30)
    assert f.host_stamp == 5.0
    assert f.depth_m()[0, 0] == pytest.approx(1.002)
    rs.STATE.metadata = False  # firmware without metadata: get_timestamp() ms
    assert c.read().device_stamp == pytest.approx(1.0 + 3 / 30)


def test_device_stamp_is_unwrapped_across_the_32_bit_counter_wrap(rs):
    rs.STATE.stamp_offset_us = (1 << 32) - 1_000_000 - 3 * 33_333  # the counter wraps after a few frames
    c = cam()
    c.connect()
    stamps = [c.read().device_stamp for _ in range(6)]
    assert all(b - a == pytest.approx(1 / 30, abs=1e-5) for a, b in zip(stamps, stamps[1:], strict=False))
    assert stamps[-1] > 4294.0  # past 2**32 µs, not back near 0


def test_laser_power_is_clamped_and_rounded_to_the_option_step(rs):
    from drivers.realsense import snap_option

    assert snap_option(160.0, 0.0, 360.0, 30.0) == 150.0
    assert snap_option(170.0, 0.0, 360.0, 30.0) == 180.0
    assert snap_option(400.0, 0.0, 360.0, 30.0) == 360.0
    assert snap_option(355.0, 0.0, 350.0, 30.0) == 330.0  # never above the range
    c = cam(laser_power=359.0)
    c.connect()
    assert rs.STATE.options["laser_power"] == 360.0


def test_recover_without_a_device_does_not_claim_a_reset(rs, monkeypatch):
    c = cam(serial="999")
    rs.STATE.start_failures = 10
    monkeypatch.setattr(rs.context, "query_devices", lambda self: [])
    with pytest.raises(DeviceError, match="no RealSense device with serial 999") as info:
        c.recover()
    assert "reset;" not in str(info.value) and rs.STATE.resets == 0


def test_frame_timeout_raises_then_recover_restarts(rs):
    c = cam()
    c.connect()
    rs.STATE.stall = 1
    with pytest.raises(DeviceError, match="no frame within") as info:
        c.read(timeout=0.2)
    assert info.value.recoverable
    c.recover()
    assert rs.STATE.starts == 2
    assert c.read().frame_number > 0


def test_recover_resets_the_device_when_restart_fails(rs):
    c = cam()
    c.connect()
    rs.STATE.start_failures = 1
    with pytest.raises(DeviceError, match="reset"):
        c.recover()
    assert rs.STATE.resets == 1
    c.recover()  # after re-enumeration
    c.read()


def test_unsupported_mode_is_a_device_error(rs):
    rs.STATE.start_failures = 1
    with pytest.raises(DeviceError, match="cannot start"):
        cam().connect()


def test_intrinsics_before_connect_are_nominal(rs):
    k = cam().intrinsics
    assert (k.width, k.height) == (640, 360) and k.fx > 0


def test_missing_pyrealsense2_raises_driver_unavailable(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    with pytest.raises(DriverUnavailable, match=r"pip install 'trackdeform3d\[realsense\]'"):
        cam().connect()
