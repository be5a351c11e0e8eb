"""URArm against fake ur-rtde modules: servoJ streaming, timing, protective stop and recovery."""

from __future__ import annotations

import sys
import time

import numpy as np
import pytest

from drivers.base import DeviceError, DriverUnavailable, create_arm
from drivers.config import URArmConfig
from tdcommon.types import JointMotion
from tests.doubles import fake_rtde


@pytest.fixture
def rtde(monkeypatch):
    mods = fake_rtde.make_modules()
    for name, mod in mods.items():
        monkeypatch.setitem(sys.modules, name, mod)
    return fake_rtde


def ramp(delta: float, duration: float, dt: float = 0.01) -> JointMotion:
    """Joint 0 (and the ignored 7th joint) ramp by ``delta`` rad over ``duration`` s from zero."""
    times = np.arange(0.0, duration + 1e-9, dt)
    q = np.zeros((len(times), 7))
    q[:, 0] = delta * times / duration
    q[:, 6] = 0.3  # a 7th program column the UR must ignore
    dq = np.gradient(q, dt, axis=0)
    return JointMotion(times, q, dq, q[-1:].copy(), np.array([duration]), np.array([0.05]))


def arm(host: str = "192.168.1.10", **kw):
    return create_arm(URArmConfig(host=host, **kw), name="left")


def test_connect_and_state_pads_seventh_joint(rtde):
    a = arm()
    a.connect()
    st = a.read_state()
    assert st.q.shape == (7,) and st.dq.shape == (7,) and st.q[6] == 0.0
    assert "control.__init__(500)" in rtde.sim_for("192.168.1.10").calls
    a.close()
    a.close()


def test_servoj_stream_resamples_at_servo_rate(rtde):
    a = arm(servo_rate=250.0, lookahead_time=0.05, gain=500.0)
    a.connect()
    assert "control.__init__(250)" in rtde.sim_for("192.168.1.10").calls
    m = ramp(0.2, 0.2)
    a.start_motion(m)
    assert not a.wait_motion(0.0)  # returns at once, streaming in the background
    assert a.wait_motion(timeout=5.0)
    calls = rtde.sim_for("192.168.1.10").servo_calls
    # 0.2 s at 250 Hz -> 51 set-points, plus a lookahead (0.05 s = 13 periods) holding the end
    assert len(calls) == 51 + 13
    _, q, speed, acc, dt, lookahead, gain = calls[25]
    assert len(q) == 6 and q[0] == pytest.approx(0.1, abs=1e-9)
    assert dt == pytest.approx(1 / 250) and lookahead == 0.05 and gain == 500.0
    assert calls[-1][1][0] == pytest.approx(0.2)
    stamps = np.array([c[0] for c in calls])
    assert stamps[-1] - stamps[0] >= 0.95 * (len(calls) - 1) / 250  # paced by waitPeriod, never faster
    assert any(c.startswith("servoStop") for c in rtde.sim_for("192.168.1.10").calls)
    assert a.read_state().q[0] == pytest.approx(0.2)


def test_two_arms_stream_concurrently(rtde):
    left, right = arm("192.168.1.10"), arm("192.168.1.11")
    left.connect()
    right.connect()
    m = ramp(0.1, 0.1)
    left.start_motion(m)
    right.start_motion(m)
    assert left.wait_motion(5.0) and right.wait_motion(5.0)
    first = [rtde.sim_for(h).servo_calls[0][0] for h in ("192.168.1.10", "192.168.1.11")]
    assert abs(first[0] - first[1]) < 0.1


def test_protective_stop_then_recover_and_retry(rtde):
    a = arm()
    a.connect()
    sim = rtde.sim_for("192.168.1.10")
    sim.protective_stop_after = 10
    a.start_motion(ramp(0.1, 0.2))
    with pytest.raises(DeviceError, match="protective stop") as info:
        a.wait_motion(timeout=5.0)
    assert info.value.recoverable
    with pytest.raises(DeviceError, match="protective stop"):
        a.start_motion(ramp(0.1, 0.2))
    a.recover()
    assert sim.calls.index("unlockProtectiveStop") < sim.calls.index("reuploadScript")
    # the arm stopped part-way: plan from where it is
    q0 = a.read_state().q
    m = ramp(0.1, 0.1)
    m = JointMotion(m.times, m.q + np.r_[q0[:6], 0.0], m.dq, m.targets + np.r_[q0[:6], 0.0], m.durations,
                    m.limit_scale)
    a.start_motion(m)
    assert a.wait_motion(timeout=5.0)


def test_emergency_stop_is_not_recoverable(rtde):
    a = arm()
    a.connect()
    rtde.sim_for("192.168.1.10").emergency = True
    with pytest.raises(DeviceError) as info:
        a.start_motion(ramp(0.1, 0.1))
    assert not info.value.recoverable
    with pytest.raises(DeviceError) as info:
        a.recover()
    assert not info.value.recoverable


def test_lost_connection_during_streaming(rtde):
    a = arm()
    a.connect()
    sim = rtde.sim_for("192.168.1.10")
    a.start_motion(ramp(0.1, 1.0))
    time.sleep(0.05)
    sim.connected = False
    with pytest.raises(DeviceError, match="servoJ failed") as info:
        a.wait_motion(timeout=5.0)
    assert info.value.recoverable
    a.recover()
    assert "control.reconnect" in sim.calls


def test_stop_aborts_streaming(rtde):
    a = arm()
    a.connect()
    a.start_motion(ramp(0.1, 5.0))
    time.sleep(0.02)
    t0 = time.monotonic()
    a.stop()
    assert time.monotonic() - t0 < 0.5
    assert a.wait_motion(0.1)
    assert len(rtde.sim_for("192.168.1.10").servo_calls) < 500


def test_motion_must_start_at_current_state(rtde):
    a = arm()
    a.connect()
    m = ramp(0.1, 0.1)
    bad = JointMotion(m.times, m.q + 0.5, m.dq, m.targets + 0.5, m.durations, m.limit_scale)
    with pytest.raises(DeviceError, match="rad from the current"):
        a.start_motion(bad)


def test_missing_ur_rtde_raises_driver_unavailable(monkeypatch):
    monkeypatch.setitem(sys.modules, "rtde_control", None)
    with pytest.raises(DriverUnavailable, match=r"pip install 'trackdeform3d\[ur\]'"):
        arm().connect()
