"""URArm against the real ur-rtde: its interfaces decide which methods and arguments the driver may use.

No robot: the simulated controller of tests/doubles/fake_rtde supplies the behaviour, but every
interface object the driver gets is the double seen through the real ``RTDEControlInterface`` /
``RTDEReceiveInterface`` / ``DashboardClient`` (only their method names, calls checked against
their pybind11 signatures, e.g. ``waitPeriod`` takes ``initPeriod()``'s timedelta). The
driver's motion, protective-stop and reconnect flows of tests/test_drivers_ur.py run that way.
Connecting the real interfaces to a host with no controller must raise DeviceError.
"""

from __future__ import annotations

import sys
import types

import pytest

from drivers.base import DeviceError
from drivers.config import URArmConfig
from drivers.ur import URArm
from tests import test_drivers_ur as flows
from tests.doubles import fake_rtde
from tests.pybind_signatures import checked_class, overloads

rtde_control = pytest.importorskip("rtde_control", reason="ur-rtde is not installed (pip install '.[ur]')")
rtde_receive = pytest.importorskip("rtde_receive", reason="ur-rtde is not installed (pip install '.[ur]')")
dashboard_client = pytest.importorskip("dashboard_client", reason="ur-rtde is not installed (pip install '.[ur]')")
pytestmark = pytest.mark.real_sdk

REAL = {
    "rtde_control": ("RTDEControlInterface", rtde_control),
    "rtde_receive": ("RTDEReceiveInterface", rtde_receive),
    "dashboard_client": ("DashboardClient", dashboard_client),
}


@pytest.fixture
def checked_rtde(monkeypatch):
    """sys.modules' ur-rtde replaced by the simulated controller behind the real interfaces' surface."""
    fakes = fake_rtde.make_modules()
    for name, (cls_name, real_module) in REAL.items():
        mod = types.ModuleType(name)
        setattr(mod, cls_name, checked_class(getattr(fakes[name], cls_name), getattr(real_module, cls_name),
                                             real_module))
        monkeypatch.setitem(sys.modules, name, mod)
    return fake_rtde


FLOWS = [
    flows.test_connect_and_state_pads_seventh_joint,
    flows.test_servoj_stream_resamples_at_servo_rate,
    flows.test_protective_stop_then_recover_and_retry,
    flows.test_emergency_stop_is_not_recoverable,
    flows.test_lost_connection_during_streaming,
    flows.test_stop_aborts_streaming,
]


@pytest.mark.parametrize("flow", FLOWS, ids=[f.__name__.removeprefix("test_") for f in FLOWS])
def test_driver_flows_use_only_the_real_interfaces_methods_and_signatures(flow, checked_rtde):
    flow(checked_rtde)


def test_servoj_is_positional_with_six_arguments_in_the_real_binding():
    (params,) = overloads(rtde_control.RTDEControlInterface.servoJ)
    assert [p.type for p in params] == ["list[float]", "float", "float", "float", "float", "float"]
    (params,) = overloads(rtde_control.RTDEControlInterface.waitPeriod)
    assert params[0].type == "datetime.timedelta"


def test_connecting_the_real_interfaces_to_a_host_without_a_controller_is_a_device_error():
    a = URArm(URArmConfig(host="127.0.0.1"), name="left")  # nothing listens on the RTDE port 30004 here
    with pytest.raises(DeviceError, match="cannot connect to 127.0.0.1") as info:
        a.connect()
    assert info.value.recoverable
    a.close()
