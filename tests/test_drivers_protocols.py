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


SDKS = ("franky", "rtde_control", "rtde_receive", "pyrealsense2", "depthai", "serial")


@pytest.mark.parametrize(("kind", "type_name", "config", "protocol"), CASES)
def test_driver_builds_without_sdk_and_matches_protocol(kind, type_name, config, protocol, monkeypatch):
    """Building a driver (and closing it unconnected) imports no vendor SDK: with every SDK made
    unimportable (``sys.modules[name] = None`` makes ``import name`` raise), it still works."""
    for sdk in SDKS:
        monkeypatch.setitem(sys.modules, sdk, None)
    cls = driver_class(kind, type_name)
    dev = cls(config, name="x", clock=None)
    assert isinstance(dev, protocol)
    dev.close()  # closing a never-connected driver is harmless
    assert all(sys.modules[sdk] is None for sdk in SDKS)  # nothing replaced the blocked entries


def test_connect_without_the_sdk_names_the_extra(monkeypatch):
    """Connecting a driver whose SDK is missing says which extra installs it."""
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    dev = driver_class("camera", "realsense")(RealSenseCameraConfig(), name="x", clock=None)
    with pytest.raises(DriverUnavailable, match="realsense"):
        dev.connect()


def test_franky_refuses_to_load_next_to_pylibfranka(monkeypatch):
    from drivers.franka import import_franky

    monkeypatch.setitem(sys.modules, "pylibfranka", types.ModuleType("pylibfranka"))
    with pytest.raises(DriverUnavailable, match="pylibfranka"):
        import_franky()
