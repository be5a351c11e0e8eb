"""The SDK doubles in tests/doubles offer only what the real SDKs have.

Each double (module, class, enum, namespace, sample instance) is walked and every public
name it offers must exist on the real counterpart, recursively through nested classes; a
name the double needs for itself (state, fault injection) is listed in its ``DOUBLE_ONLY``.
A keyword default the double gives a method must equal the real pybind11 default. Each
SDK's check is skipped only when that SDK is not installed.
"""

from __future__ import annotations

import enum
import inspect
import sys
import types
from typing import Any

import pytest

from tests.doubles import fake_depthai, fake_franky, fake_realsense, fake_rtde, fake_serial
from tests.pybind_signatures import overloads

pytestmark = pytest.mark.real_sdk


def _own_names(obj: Any, module: str) -> set[str]:
    """Public names ``obj`` defines itself (a class: its own and double bases' members; else its attributes)."""
    if isinstance(obj, type):
        if issubclass(obj, enum.Enum):
            return set(obj.__members__)
        names: set[str] = set()
        for klass in obj.__mro__:
            if klass.__module__ == module:
                names |= set(vars(klass))
        return {n for n in names if not n.startswith("_")}
    if isinstance(obj, types.ModuleType | types.SimpleNamespace):
        return {n for n in vars(obj) if not n.startswith("_")}
    names = _own_names(type(obj), module)
    return names | {n for n in vars(obj) if not n.startswith("_")}


def _double_only(obj: Any, module: str) -> set[str]:
    extra = set(getattr(obj, "DOUBLE_ONLY", ()))
    if isinstance(obj, types.ModuleType):  # a module a double's make_module() built: its source's list
        extra |= set(getattr(sys.modules[module], "DOUBLE_ONLY", ()))
    if not isinstance(obj, type | types.ModuleType | types.SimpleNamespace):
        extra |= set(getattr(type(obj), "DOUBLE_ONLY", ()))
    return extra | {"DOUBLE_ONLY"}


def _defaults_differ(double_fn: Any, real_fn: Any, name: str) -> list[str]:
    """Keyword defaults of ``double_fn`` that differ from the real pybind11 defaults of the same parameter."""
    try:
        sig = inspect.signature(double_fn)
    except (TypeError, ValueError):
        return []
    real = {p.name: p.default for ov in overloads(real_fn, name) for p in ov if p.has_default}
    out = []
    for p in sig.parameters.values():
        if p.default is inspect.Parameter.empty or p.name not in real:
            continue
        if isinstance(p.default, bool | int | float) and real[p.name] in ("True", "False") or (
                isinstance(p.default, int | float) and not isinstance(p.default, bool)
                and real[p.name].replace(".", "", 1).lstrip("-").isdigit()):
            if repr(p.default) != real[p.name] and not (
                    isinstance(p.default, float) and float(real[p.name]) == p.default):
                out.append(f"{name}({p.name}={p.default!r}) but the real default is {real[p.name]}")
    return out


def walk(double: Any, real: Any, path: str, module: str, problems: list[str], seen: set[int]) -> None:
    """Check every public name of ``double`` on ``real``; recurse into the double's own classes/namespaces."""
    if id(double) in seen:
        return
    seen.add(id(double))
    for name in sorted(_own_names(double, module) - _double_only(double, module)):
        if not hasattr(real, name):
            problems.append(f"{path}.{name}: the double offers it, the real SDK has no such name")
            continue
        value = getattr(double, name, None)
        real_value = getattr(real, name)
        if inspect.isfunction(value) and callable(real_value):
            problems += [f"{path}.{msg}" for msg in _defaults_differ(value, real_value, name)]
        if isinstance(value, type) and value.__module__ == module or isinstance(value, types.SimpleNamespace):
            walk(value, real_value, f"{path}.{name}", module, problems, seen)


def check(pairs: list[tuple[Any, Any, str]], module: str) -> None:
    problems: list[str] = []
    seen: set[int] = set()
    for double, real, path in pairs:
        walk(double, real, path, module, problems, seen)
    assert not problems, "doubles drifted from the real SDK:\n  " + "\n  ".join(problems)


def test_depthai_double_matches_depthai():
    dai = pytest.importorskip("depthai", reason="depthai is not installed (pip install '.[oak]')")
    mod = fake_depthai.make_module()
    fake_depthai.STATE.color_size = (64, 48)
    group = fake_depthai.MessageQueue().tryGet()
    check([
        (mod, dai, "depthai"),
        (fake_depthai.Node.Output("x"), dai.Node.Output, "depthai.Node.Output()"),
        (group["color"], dai.ImgFrame, "depthai.ImgFrame()"),
        (fake_depthai.DeviceInfo("x"), dai.DeviceInfo, "depthai.DeviceInfo()"),
        (fake_depthai.Camera("c"), dai.node.Camera, "depthai.node.Camera()"),
        (fake_depthai.StereoDepth("s"), dai.node.StereoDepth, "depthai.node.StereoDepth()"),
        (fake_depthai.Sync("y"), dai.node.Sync, "depthai.node.Sync()"),
    ], fake_depthai.__name__)


def test_franky_double_matches_franky():
    franky = pytest.importorskip("franky", reason="franky-control is not installed (pip install '.[franka]')")
    mod = fake_franky.make_module()
    wp = fake_franky.JointWaypoint([0.0] * 7, minimum_time=fake_franky.Duration(5))
    check([
        (mod, franky, "franky"),
        (fake_franky.Duration(5), franky.Duration, "franky.Duration()"),
        (wp, franky.JointWaypoint, "franky.JointWaypoint()"),
        (fake_franky.JointWaypointMotion([wp]), franky.JointWaypointMotion, "franky.JointWaypointMotion()"),
        (fake_franky.JointStopMotion(), franky.JointStopMotion, "franky.JointStopMotion()"),
        (fake_franky.RelativeDynamicsFactor(0.5), franky.RelativeDynamicsFactor, "franky.RelativeDynamicsFactor()"),
        (fake_franky.Robot("172.16.0.2"), franky.Robot, "franky.Robot()"),
        (fake_franky.Gripper("172.16.0.2"), franky.Gripper, "franky.Gripper()"),
        (fake_franky.GripperState(0.01, 0.08, True), franky.GripperState, "franky.GripperState()"),
        (fake_franky.BoolFuture(True), franky.BoolFuture, "franky.BoolFuture()"),
    ], fake_franky.__name__)
    exceptions = {n for n in dir(franky) if isinstance(getattr(franky, n), type)
                  and issubclass(getattr(franky, n), BaseException)}
    missing = exceptions - set(vars(mod))
    assert not missing, f"the franky double lacks the real exceptions {sorted(missing)}"
    for name in exceptions:  # and mirrors their hierarchy
        real_base = issubclass(getattr(franky, name), franky.Exception)
        assert issubclass(getattr(mod, name), mod.Exception) == real_base, name


def test_rtde_doubles_match_ur_rtde():
    real = {n: pytest.importorskip(n, reason="ur-rtde is not installed (pip install '.[ur]')")
            for n in ("rtde_control", "rtde_receive", "dashboard_client")}
    mods = fake_rtde.make_modules()
    check([(mods[n], real[n], n) for n in real] + [
        (fake_rtde.RTDEControlInterface("h"), real["rtde_control"].RTDEControlInterface, "RTDEControlInterface()"),
        (fake_rtde.RTDEReceiveInterface("h"), real["rtde_receive"].RTDEReceiveInterface, "RTDEReceiveInterface()"),
        (fake_rtde.DashboardClient("h"), real["dashboard_client"].DashboardClient, "DashboardClient()"),
    ], fake_rtde.__name__)


def test_realsense_double_matches_pyrealsense2():
    rs = pytest.importorskip("pyrealsense2", reason="pyrealsense2 is not installed (pip install '.[realsense]')")
    mod = fake_realsense.make_module()
    cfg = mod.config()
    cfg.enable_stream(mod.stream.color, 64, 48, mod.format.rgb8, 30)
    profile = mod.pipeline().start(cfg)
    frames = mod.pipeline()
    frames.cfg = cfg
    fs = frames.wait_for_frames()
    check([
        (mod, rs, "pyrealsense2"),
        (cfg, rs.config, "pyrealsense2.config()"),
        (fake_realsense._Sensor(), rs.depth_sensor, "depth_sensor"),
        (fake_realsense._Device(), rs.device, "device"),
        (profile, rs.pipeline_profile, "pipeline_profile"),
        (profile.get_stream(mod.stream.color), rs.video_stream_profile, "video_stream_profile"),
        (profile.get_stream(mod.stream.color).get_intrinsics(), rs.intrinsics, "intrinsics"),
        (fs, rs.composite_frame, "composite_frame"),
        (fs.get_color_frame(), rs.video_frame, "video_frame"),
        (fake_realsense._Sensor().get_option_range(mod.option.laser_power), rs.option_range, "option_range"),
    ], fake_realsense.__name__)


def test_serial_double_matches_pyserial():
    serial = pytest.importorskip("serial", reason="pyserial is not installed")
    mod = fake_serial.make_module(fake_serial.RobotiqSim())
    check([
        (mod, serial, "serial"),
        (mod.Serial(port="/dev/null"), serial.Serial, "serial.Serial()"),
    ], fake_serial.__name__)


def test_the_surface_check_catches_a_drifted_double():
    """The walker itself: a name the real class lacks, and a wrong keyword default, are reported."""
    franky = pytest.importorskip("franky", reason="franky-control is not installed (pip install '.[franka]')")
    dai = pytest.importorskip("depthai", reason="depthai is not installed (pip install '.[oak]')")

    class Duration:
        def __init__(self, ms: int) -> None:
            self.ms = ms

    class Output:
        def createOutputQueue(self, maxSize: int = 16, blocking: bool = True) -> None:  # noqa: N802, N803
            return None

    with pytest.raises(AssertionError, match=r"Duration\(\)\.ms: the double offers it"):
        check([(Duration(5), franky.Duration, "Duration()")], __name__)
    with pytest.raises(AssertionError, match="blocking=True.*real default is False"):
        check([(Output, dai.Node.Output, "Output")], __name__)
