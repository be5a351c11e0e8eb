"""FrankaArm / FrankaHand against a fake ``franky`` module (no robot, no SDK)."""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import pytest

from drivers.base import DeviceError, DriverUnavailable, create_arm, create_gripper
from drivers.config import FrankaArmConfig, FrankaHandConfig
from drivers.franka import FrankaArm, FrankaHand
from tdcommon.types import JointMotion
from tests.doubles import fake_franky

HOME = fake_franky.Robot.initial_q.copy()


@pytest.fixture
def franky(monkeypatch):
    mod = fake_franky.make_module()
    monkeypatch.setitem(sys.modules, "franky", mod)
    return mod


def motion(start: np.ndarray, deltas: list[float], durations: list[float], scale: float = 0.02) -> JointMotion:
    """A rest-to-rest motion through ``start + delta`` targets (samples by linear interpolation)."""
    targets = np.array([start + d for d in deltas])
    knots = np.vstack([start, targets])
    t_knots = np.concatenate([[0.0], np.cumsum(durations)])
    times = np.arange(0.0, t_knots[-1] + 1e-9, 0.01)
    q = np.stack([np.interp(times, t_knots, knots[:, j]) for j in range(7)], axis=1)
    return JointMotion(times, q, np.gradient(q, 0.01, axis=0), targets, np.array(durations),
                       np.full(len(durations), scale))


def arm(host: str = "172.16.0.2", **kw) -> FrankaArm:
    return create_arm(FrankaArmConfig(host=host, **kw), name="left")


def test_connect_sets_dynamics_and_reads_state(franky):
    a = arm(relative_dynamics=0.3)
    a.connect()
    robot = franky.Robot.instances[0]
    assert robot.host == "172.16.0.2"
    assert ("relative_dynamics_factor", 0.3) in [(c[1], c[2]) for c in robot.calls]
    st = a.read_state()
    assert st.q.shape == (7,) and np.allclose(st.q, HOME)
    a.close()
    a.close()


def test_motion_becomes_waypoints_with_minimum_times(franky):
    a = arm(relative_dynamics=0.5)
    a.connect()
    m = motion(HOME, [0.1, 0.2, 0.0], [0.4, 0.2, 0.3], scale=0.02)
    a.start_motion(m)
    robot = franky.Robot.instances[0]
    (fm, asynchronous) = [c[2] for c in robot.calls if c[1] == "move"][0]
    assert asynchronous is True
    assert len(fm.waypoints) == 3
    assert [w.minimum_time.to_msec() for w in fm.waypoints] == [400, 200, 300]
    assert np.allclose(fm.waypoints[1].target.position, HOME + 0.2)
    f = fm.waypoints[0].relative_dynamics_factor
    assert f.velocity == 1.0 and f.acceleration == pytest.approx(0.04) and f.jerk == pytest.approx(0.04)
    assert a.wait_motion(timeout=2.0)
    assert np.allclose(a.read_state().q, HOME)  # back at the last target


def test_dwell_segment_holds_its_target(franky):
    a = arm()
    a.connect()
    m = motion(HOME, [0.1, 0.1], [0.5, 1.0])
    m = JointMotion(m.times, m.q, m.dq, m.targets, m.durations, np.array([0.02, 0.0]))
    a.start_motion(m)
    fm = [c[2][0] for c in franky.Robot.instances[0].calls if c[1] == "move"][0]
    first, dwell = fm.waypoints
    assert first.minimum_time.to_msec() == 500 and first.hold_target_duration.to_msec() == 0
    assert dwell.minimum_time is None and dwell.hold_target_duration.to_msec() == 1000
    f = dwell.relative_dynamics_factor
    assert (f.velocity, f.acceleration, f.jerk) == (1.0, 1.0, 1.0)
    assert a.wait_motion(2.0)


def test_wait_motion_times_out_while_running(franky):
    a = arm()
    a.connect()
    a.start_motion(motion(HOME, [0.1], [4.0]))  # 0.2 s at the fake's time scale
    assert a.wait_motion(timeout=0.01) is False
    assert a.wait_motion(timeout=2.0) is True


def test_two_arms_start_asynchronously_together(franky):
    left, right = arm("172.16.0.2"), arm("172.16.1.2")
    left.connect()
    right.connect()
    m = motion(HOME, [0.1], [10.0])  # 0.5 s at the fake's time scale
    left.start_motion(m)
    right.start_motion(m)
    assert not left.wait_motion(0.0) and not right.wait_motion(0.0)  # both run at once
    moves = [[c for c in r.calls if c[1] == "move"] for r in franky.Robot.instances]
    assert all(len(mv) == 1 and mv[0][2][1] is True for mv in moves)  # asynchronous=True
    assert abs(moves[0][0][0] - moves[1][0][0]) < 0.1
    assert left.wait_motion(2.0) and right.wait_motion(2.0)


def test_reflex_raises_recoverable_error_then_recover_and_retry(franky):
    a = arm(recover_on_reflex=False)
    a.connect()
    robot = franky.Robot.instances[0]
    robot.fault = franky.ControlException("libfranka: Move command aborted: motion aborted by reflex! "
                                          "[\"cartesian_reflex\"]")
    m = motion(HOME, [0.1], [1.0])
    a.start_motion(m)
    with pytest.raises(DeviceError) as info:
        a.wait_motion(timeout=2.0)
    assert info.value.recoverable and "reflex" in str(info.value)
    with pytest.raises(DeviceError) as info:  # still in reflex mode: the next move is refused
        a.start_motion(m)
    assert info.value.recoverable
    a.recover()
    assert ("recover_from_errors", None) in [(c[1], c[2]) for c in robot.calls]
    a.start_motion(m)
    assert a.wait_motion(timeout=2.0)


def test_recover_on_reflex_clears_the_error_at_once(franky):
    a = arm(recover_on_reflex=True)
    a.connect()
    robot = franky.Robot.instances[0]
    robot.fault = franky.ControlException("reflex")
    a.start_motion(motion(HOME, [0.1], [1.0]))
    with pytest.raises(DeviceError):
        a.wait_motion(timeout=2.0)
    assert not robot.has_errors


def test_network_loss_recovers_by_reconnecting(franky):
    a = arm()
    a.connect()
    franky.Robot.instances[0].disconnected = True
    with pytest.raises(DeviceError) as info:
        a.read_state()
    assert info.value.recoverable
    a.recover()
    assert len(franky.Robot.instances) == 2
    assert np.allclose(a.read_state().q, HOME)


def test_incompatible_version_is_not_recoverable(franky):
    franky.Robot.connect_error = franky.IncompatibleVersionException(
        "libfranka: Incompatible library version (server version: 5, library version: 9)")
    with pytest.raises(DeviceError) as info:
        arm().connect()
    assert not info.value.recoverable


def test_motion_must_start_at_current_state(franky):
    a = arm()
    a.connect()
    with pytest.raises(DeviceError, match="rad from the current"):
        a.start_motion(motion(HOME + 0.3, [0.1], [1.0]))


def test_stop_sends_a_joint_stop_motion(franky):
    a = arm()
    a.connect()
    a.start_motion(motion(HOME, [0.1], [10.0]))
    a.stop()
    moves = [c[2][0] for c in franky.Robot.instances[0].calls if c[1] == "move"]
    assert isinstance(moves[-1], franky.JointStopMotion)


def test_missing_franky_raises_driver_unavailable(monkeypatch):
    monkeypatch.setitem(sys.modules, "franky", None)
    with pytest.raises(DriverUnavailable, match=r"pip install 'trackdeform3d\[franka\]'"):
        arm().connect()


def test_hand_homes_then_grasps_and_opens(franky):
    a = arm("172.16.0.2")
    hand = create_gripper(FrankaHandConfig(force=25.0, speed=0.04), name="left_hand", arm_config=a.config)
    assert isinstance(hand, FrankaHand)
    hand.connect()
    g = franky.Gripper.instances[0]
    assert g.host == "172.16.0.2" and g.calls[0][0] == "homing"
    hand.command(closed=True)
    name, args, kwargs = g.calls[-1]
    assert name == "grasp_async" and args == (0.0, 0.04, 25.0) and kwargs["epsilon_outer"] == 1.0
    assert hand.wait(1.0) is True
    st = wait_for(hand, lambda s: s.grasped)
    assert st.width == pytest.approx(0.02)
    hand.command(closed=False)
    assert g.calls[-1][:2] == ("move_async", (0.08, 0.04))
    st = wait_for(hand, lambda s: not s.grasped)
    assert st.width == pytest.approx(0.08)
    hand.close()
    hand.close()


def wait_for(hand, cond, timeout: float = 1.0):
    """The hand's state once ``cond`` holds (the state reader runs on its own thread)."""
    deadline = time.monotonic() + timeout
    while True:
        st = hand.read_state()
        if cond(st) or time.monotonic() > deadline:
            return st
        time.sleep(0.002)


def test_hand_state_errors_surface_and_recover(franky):
    hand = create_gripper(FrankaHandConfig(host="172.16.0.2"), name="h")
    hand.connect()
    g = franky.Gripper.instances[0]
    g.fail = True
    deadline = time.monotonic() + 5.0  # the hand's state thread sees the failure at its next poll
    with pytest.raises(DeviceError, match="GripperException"):
        while time.monotonic() < deadline:
            hand.read_state()
            time.sleep(0.01)
    g.fail = False
    hand.recover()
    assert ("stop", (), {}) in g.calls
    assert not hand.read_state().grasped
    hand.close()


def test_hand_needs_a_host(franky):
    hand = FrankaHand(FrankaHandConfig(), name="h")
    with pytest.raises(DeviceError, match="no host"):
        hand.connect()


def test_state_reads_are_safe_during_motion(franky):
    a = arm()
    a.connect()
    a.start_motion(motion(HOME, [0.1], [2.0]))
    errors: list[BaseException] = []

    def reader() -> None:
        try:
            for _ in range(50):
                a.read_state()
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    th = threading.Thread(target=reader)
    th.start()
    assert a.wait_motion(2.0)
    th.join()
    assert not errors
