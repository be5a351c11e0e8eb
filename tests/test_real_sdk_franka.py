"""FrankaArm / FrankaHand against the real franky: real motions, waypoints, durations and exceptions.

No robot: ``Robot`` and ``Gripper`` are the simulated ones of tests/doubles/fake_franky seen
through the real ``franky.Robot`` / ``franky.Gripper`` (only their names, calls checked
against their pybind11 signatures) and raising the real franky exceptions; everything the
driver builds (``JointWaypointMotion``, ``JointWaypoint``, ``Duration``,
``RelativeDynamicsFactor``, ``JointStopMotion``) is the real class. The real ``Robot`` and
``Gripper`` connecting to a host without a controller must raise DeviceError. Never import
pylibfranka in this process (pybind11 type clash with franky).
"""

from __future__ import annotations

import sys
import types

import pytest

from drivers.base import DeviceError
from drivers.config import FrankaArmConfig, FrankaHandConfig
from drivers.franka import FrankaArm, FrankaHand, _franky_errors, _FrankyErrors
from tests import test_drivers_franka as flows
from tests.doubles import fake_franky
from tests.pybind_signatures import Checked, check_call

if "pylibfranka" in sys.modules:
    pytest.skip("pylibfranka is loaded in this process; franky cannot be used with it", allow_module_level=True)
franky = pytest.importorskip("franky", reason="franky-control is not installed (pip install '.[franka]')")
pytestmark = pytest.mark.real_sdk

FAKE_RAISES = ("NetworkException", "CommandException", "GripperException")


class _Factory:
    """Stands for franky.Robot / franky.Gripper: constructor checked, the simulated object wrapped in Checked."""

    def __init__(self, double_cls: type, real_cls: type) -> None:
        self.double_cls, self.real_cls = double_cls, real_cls

    def __call__(self, *args, **kwargs) -> Checked:
        check_call(franky, self.real_cls.__init__, args, kwargs, "__init__")
        return Checked(self.double_cls(*args, **kwargs), self.real_cls, franky)

    @property
    def instances(self) -> list:
        return self.double_cls.instances


@pytest.fixture
def checked_franky(monkeypatch):
    fake_franky.make_module()  # resets the simulated robots
    for name in FAKE_RAISES:  # the simulated robot raises the real exceptions
        monkeypatch.setattr(fake_franky, name, getattr(franky, name))
    mod = types.ModuleType("franky")
    for name in dir(franky):
        if not name.startswith("__"):
            setattr(mod, name, getattr(franky, name))
    mod.Robot = _Factory(fake_franky.Robot, franky.Robot)
    mod.Gripper = _Factory(fake_franky.Gripper, franky.Gripper)
    monkeypatch.setitem(sys.modules, "franky", mod)
    return mod


FLOWS = [
    flows.test_connect_sets_dynamics_and_reads_state,
    flows.test_motion_becomes_waypoints_with_minimum_times,
    flows.test_dwell_segment_holds_its_target,
    flows.test_reflex_raises_recoverable_error_then_recover_and_retry,
    flows.test_network_loss_recovers_by_reconnecting,
    flows.test_stop_sends_a_joint_stop_motion,
    flows.test_hand_homes_then_grasps_and_opens,
    flows.test_hand_state_errors_surface_and_recover,
]


@pytest.mark.parametrize("flow", FLOWS, ids=[f.__name__.removeprefix("test_") for f in FLOWS])
def test_driver_flows_with_the_real_motion_classes_and_exceptions(flow, checked_franky):
    flow(checked_franky)


def test_build_motion_returns_real_franky_objects():
    arm = FrankaArm(FrankaArmConfig(host="172.16.0.2", relative_dynamics=0.5), name="left")
    arm._franky = franky
    m = flows.motion(flows.HOME, [0.1, 0.2], [0.4, 0.6], scale=0.02)
    fm = arm.build_motion(m)
    assert isinstance(fm, franky.JointWaypointMotion)
    assert all(isinstance(w, franky.JointWaypoint) for w in fm.waypoints)
    assert all(isinstance(w.minimum_time, franky.Duration) for w in fm.waypoints)
    assert [w.minimum_time.to_msec() for w in fm.waypoints] == [400, 600]
    assert fm.waypoints[0].relative_dynamics_factor.acceleration == pytest.approx(0.04)


def test_every_franky_exception_is_classified():
    recoverable, fatal = _franky_errors(franky)
    classes = [getattr(franky, n) for n in dir(franky)]
    excs = [c for c in classes if isinstance(c, type) and issubclass(c, BaseException)]
    libfranka = [c for c in excs if issubclass(c, franky.Exception)]
    assert len(libfranka) >= 8  # franka::Exception and its subclasses
    for cls in libfranka + [franky.GripperException, franky.MotionReuseException,
                            franky.ReactionRecursionException, franky.InvalidMotionTypeException]:
        err = _FrankyErrors("left", "test", franky)
        with pytest.raises(DeviceError) as info, err:
            raise cls("x")
        assert info.value.recoverable == (cls not in fatal), cls
    assert {c.__name__ for c in fatal} == {"IncompatibleVersionException", "RealtimeException", "ModelException",
                                           "ProtocolException"}


def test_real_robot_and_gripper_without_a_controller_are_device_errors():
    arm = FrankaArm(FrankaArmConfig(host="127.0.0.1"), name="left")  # nothing serves FCI on the loopback
    with pytest.raises(DeviceError, match="connect to 127.0.0.1") as info:
        arm.connect()
    assert info.value.recoverable and "NetworkException" in str(info.value)
    hand = FrankaHand(FrankaHandConfig(host="127.0.0.1"), name="hand")
    with pytest.raises(DeviceError, match="connect to 127.0.0.1"):
        hand.connect()
    hand.close()
