"""SerialGripper against a simulated Robotiq 2F-85 on a fake serial port (no hardware)."""

from __future__ import annotations

import sys

import pytest

from drivers.base import DeviceError, DriverUnavailable, create_gripper
from drivers.clock import SimClock
from drivers.config import SerialGripperConfig
from drivers.serial_gripper import SerialGripper, check_crc, crc16_modbus, with_crc
from tests.doubles.fake_serial import RobotiqSim, make_module


@pytest.fixture
def sim(monkeypatch):
    sim = RobotiqSim(object_at=200)
    monkeypatch.setitem(sys.modules, "serial", make_module(sim))
    return sim


def make(**kw) -> SerialGripper:
    kw.setdefault("state_period", 0.0)
    cfg = SerialGripperConfig(port="/dev/ttyUSB0", **kw)
    return create_gripper(cfg, name="left", clock=SimClock())


def test_crc_matches_robotiq_manual_examples():
    # frames from the Robotiq 2F-85 manual (activation request and status read)
    assert with_crc(bytes.fromhex("091003E8000306000000000000")).hex() == "091003e80003060000000000007330"
    assert with_crc(bytes.fromhex("091003E8000306010000000000")).hex() == "091003e8000306010000000000" + "72e1"
    assert with_crc(bytes.fromhex("090407D00003")).hex() == "090407d00003b1ce"
    assert crc16_modbus(b"123456789") == 0x4B37  # the CRC-16/MODBUS check value
    assert check_crc(bytes.fromhex("090407D00003B1CE"))
    assert not check_crc(bytes.fromhex("090407D00003B1CF"))


def test_connect_activates_and_opens_port_with_config(sim):
    g = make(baudrate=115200, timeout=0.1)
    g.connect()
    port = sys.modules["serial"].ports[0]
    assert port.kwargs["port"] == "/dev/ttyUSB0" and port.kwargs["baudrate"] == 115200
    assert port.kwargs["timeout"] == 0.1
    assert sim.writes[:2] == [bytes(6), bytes((1, 0, 0, 0, 0, 0))]  # reset, then rACT
    assert sim.activated
    g.close()
    g.close()  # idempotent
    assert port.closed


def test_open_and_grasp_map_units_to_registers(sim):
    g = make(speed=0.15, force=235.0)
    g.connect()
    g.command(closed=False)
    assert sim.writes[-1] == bytes((0x09, 0, 0, 0, 255, 255))  # rACT|rGTO, fully open, max speed/force
    st = g.read_state()
    assert sim.position == 13  # the fingers stop at their software limit, as in the manual's example
    assert st.width == pytest.approx(0.085) and not st.grasped
    g.command(closed=False, width=0.0425)
    assert sim.writes[-1][3] == 120  # half way between gPO 13 (open) and 226 (closed)
    g.command(closed=True, force=20.0)
    assert sim.writes[-1][3] == 255 and sim.writes[-1][5] == 0  # min force -> register 0
    st = g.read_state()
    assert st.grasped  # fingers stopped on the object (gOBJ = 2)
    assert st.width == pytest.approx(g.register_to_width(200))


def test_width_follows_the_calibrated_position_range(sim):
    g = make(open_position=13, closed_position=226)
    assert g.register_to_width(13) == pytest.approx(0.085)
    assert g.register_to_width(0) == pytest.approx(0.085)  # clamped
    assert g.register_to_width(226) == pytest.approx(0.0)
    assert g.register_to_width(255) == pytest.approx(0.0)
    assert g.width_to_register(g.register_to_width(150)) == 150
    with pytest.raises(ValueError, match="closed_position"):
        SerialGripperConfig(port="/dev/ttyUSB0", open_position=200, closed_position=100)


def test_status_is_trusted_only_after_the_position_echo(monkeypatch):
    sim = RobotiqSim(object_at=100, echo_polls=2)
    monkeypatch.setitem(sys.modules, "serial", make_module(sim))
    g = make()
    g.connect()
    g.command(closed=True)
    for _ in range(10):
        st = g.read_state()
        if g.command_acknowledged:
            break
    assert st.grasped and st.width == pytest.approx(g.register_to_width(100))
    g.command(closed=False)
    stale = g.read_state()  # gPR still echoes the grasp: its gOBJ says "object while closing"
    assert not g.command_acknowledged and not stale.grasped
    g.read_state()
    st = g.read_state()
    assert g.command_acknowledged and not st.grasped and st.width == pytest.approx(0.085)


def test_state_reads_are_rate_limited(sim):
    clock = SimClock()
    g = SerialGripper(SerialGripperConfig(port="/dev/ttyUSB0", state_period=0.02), name="g", clock=clock)
    g.connect()
    reads = sim.reads
    g.read_state()
    g.read_state()
    assert sim.reads == reads + 1
    clock.sleep_until(clock.now() + 0.03)
    g.read_state()
    assert sim.reads == reads + 2
    g.command(closed=True)
    assert g.read_state().grasped  # a command invalidates the cached state
    assert sim.reads == reads + 3


def test_crc_error_is_retried(sim):
    g = make(retries=2)
    g.connect()
    port = sys.modules["serial"].ports[0]
    port.faults.extend(["crc", "timeout"])
    st = g.read_state()  # third attempt succeeds
    assert st.width == pytest.approx(0.085)
    assert g.retried == 2


def test_persistent_crc_errors_raise_device_error(sim):
    g = make(retries=2)
    g.connect()
    port = sys.modules["serial"].ports[0]
    n = len(port.sent)
    port.faults.extend(["crc"] * 3)
    with pytest.raises(DeviceError) as info:
        g.command(closed=True)
    assert info.value.recoverable
    assert len(port.sent) - n == 3  # 1 + retries
    g.recover()  # reactivation works once the line is clean
    g.command(closed=True)
    assert g.read_state().grasped


def test_timeouts_raise_device_error(sim):
    g = make(retries=1)
    g.connect()
    sys.modules["serial"].ports[0].faults.extend(["timeout"] * 2)
    with pytest.raises(DeviceError, match="no valid reply"):
        g.read_state()


def test_activation_timeout(monkeypatch):
    sim = RobotiqSim(activation_polls=10_000)
    monkeypatch.setitem(sys.modules, "serial", make_module(sim))
    g = make(activation_timeout=0.5)
    with pytest.raises(DeviceError, match="activation"):
        g.connect()


def test_missing_pyserial_raises_driver_unavailable(monkeypatch):
    monkeypatch.setitem(sys.modules, "serial", None)
    with pytest.raises(DriverUnavailable, match="pip install"):
        make().connect()
