"""The real drivers satisfy their Protocols and are reachable through the registry without SDKs."""

from __future__ import annotations

import sys
import types

import pytest

from drivers.base import Arm, DriverUnavailable, Gripper, RGBDCamera, driver_class
from drivers.config import (
    FrankaArmConfig,
    FrankaHandConfig,
    OakCameraConfig,
    RealSenseCameraConfig,
    SerialGripperConfig,
    URArmConfig,
)

CASES = [
    ("arm", "franka", FrankaArmConfig(host="172.16.0.2"), Arm),
    ("arm", "ur", URArmConfig(host="192.168.1.10"), Arm),
    ("gripper", "franka_hand", FrankaHandConfig(host="172.16.0.2"), Gripper),
    ("gripper", "serial", SerialGripperConfig(port="/dev/ttyUSB0"), Gripper),
    ("camera", "realsense", RealSenseCameraConfig(), RGBDCamera),
    ("camera", "oak", OakCameraConfig(), RGBDCamera),
]


@pytest.mark.parametrize(("kind", "type_name", "config", "protocol"), CASES)
def test_driver_builds_without_sdk_and_matches_protocol(kind, type_name, config, protocol):
    for sdk in ("franky", "rtde_control", "rtde_receive", "pyrealsense2", "depthai"):
        assert sdk not in sys.modules or sys.modules[sdk] is None or isinstance(sys.modules[sdk], types.ModuleType)
    cls = driver_class(kind, type_name)
    dev = cls(config, name="x", clock=None)
    assert isinstance(dev, protocol)
    dev.close()  # closing a never-connected driver is harmless


def test_franky_refuses_to_load_next_to_pylibfranka(monkeypatch):
    from drivers.franka import import_franky

    monkeypatch.setitem(sys.modules, "pylibfranka", types.ModuleType("pylibfranka"))
    with pytest.raises(DriverUnavailable, match="pylibfranka"):
        import_franky()
