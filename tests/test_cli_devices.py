"""``trackdeform devices``: discovery with no SDK, with the real SDKs and no hardware, a gripper on a pty."""

from __future__ import annotations

import json
import socket
import sys
import threading

import pytest

from orchestrator import cli_devices
from orchestrator.cli import main
from tests.conftest import REPO, free_port

SDK_MODULES = ("pyrealsense2", "depthai", "serial", "serial.tools", "serial.tools.list_ports")


def run(capsys, *argv: str) -> str:
    assert main(["devices", *argv]) == 0
    return capsys.readouterr().out


def test_without_any_sdk_it_says_which_extra_to_install(monkeypatch, capsys):
    for name in SDK_MODULES:
        monkeypatch.setitem(sys.modules, name, None)
    out = run(capsys)
    assert "RealSense cameras: pyrealsense2 is not installed: pip install 'trackdeform3d[realsense]'" in out
    assert "OAK cameras: depthai is not installed: pip install 'trackdeform3d[oak]'" in out
    assert "Serial ports: pyserial is not installed: pip install pyserial" in out
    report = json.loads(run(capsys, "--json"))
    assert {k: v["available"] for k, v in report.items()} == {"realsense": False, "oak": False, "serial": False}
    assert report["oak"]["install"] == "pip install 'trackdeform3d[oak]'"


@pytest.mark.real_sdk
def test_with_the_real_sdks_and_no_hardware_nothing_is_listed_cleanly(capsys):
    for name in ("pyrealsense2", "depthai"):
        pytest.importorskip(name, reason=f"{name} is not installed")
    report = json.loads(run(capsys, "--json"))
    for part in ("realsense", "oak"):
        assert report[part]["available"] and "error" not in report[part]
        if report[part]["devices"]:
            pytest.skip(f"a {part} camera is attached: this test needs none")
    assert report["realsense"]["devices"] == [] and report["oak"]["devices"] == []
    for port in report["serial"]["devices"]:  # e.g. /dev/ttyS0: probed, nothing answers
        assert port["robotiq"]["answers"] is False and port["robotiq"]["detail"]
    out = run(capsys)
    assert out.count("none found") >= 2


@pytest.mark.real_sdk
def test_a_robotiq_gripper_on_a_pty_is_found_without_writing_to_it(capsys):
    pytest.importorskip("serial", reason="pyserial is not installed")
    import os
    import pty
    import tty

    from tests.test_real_sdk_serial_gripper import RobotiqResponder

    master, slave = pty.openpty()
    tty.setraw(slave)
    responder = RobotiqResponder(master)
    responder.start()
    try:
        path = os.ttyname(slave)
        report = json.loads(run(capsys, "--port", path, "--json"))
        (entry,) = [p for p in report["serial"]["devices"] if p["port"] == path]
        assert entry["robotiq"]["answers"] and entry["robotiq"]["slave_id"] == 9
        assert entry["robotiq"]["status"]["gPO"] == 13 and not entry["robotiq"]["activated"]
        assert responder.requests and all(r[1] == 0x04 for r in responder.requests)  # reads only
        assert f"{path}  configured: Robotiq gripper (slave 9 @ 115200 baud): not activated" in run(
            capsys, "--port", path)
    finally:
        responder.stop()
        os.close(master)
        os.close(slave)


def _greeting_server(greeting: bytes) -> tuple[int, threading.Thread, socket.socket]:
    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)

    def serve() -> None:
        conn, _ = srv.accept()
        with conn:
            conn.sendall(greeting)

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    return srv.getsockname()[1], t, srv


def test_a_ur_controller_is_recognised_by_its_dashboard_greeting():
    port, t, srv = _greeting_server(b"Connected: Universal Robots Dashboard Server\n")
    try:
        ok, detail = cli_devices.probe_ur("127.0.0.1", 1.0, port=port)
    finally:
        t.join(2.0)
        srv.close()
    assert ok and "Dashboard Server" in detail
    port, t, srv = _greeting_server(b"SSH-2.0-OpenSSH_9.6\n")
    try:
        ok, detail = cli_devices.probe_ur("127.0.0.1", 1.0, port=port)
    finally:
        t.join(2.0)
        srv.close()
    assert not ok and "not the UR greeting" in detail
    ok, detail = cli_devices.probe_ur("127.0.0.1", 0.5, port=free_port())  # nothing listens
    assert not ok


def test_configured_arms_are_checked(tmp_path, capsys):
    text = (REPO / "configs" / "dual_ur_oak.yaml").read_text()
    cfg = tmp_path / "ur.yaml"
    cfg.write_text(text.replace("192.168.1.10", "127.0.0.1").replace("192.168.1.11", "127.0.0.1"))
    report = json.loads(run(capsys, "--config", str(cfg), "--timeout", "0.5", "--json"))
    assert [(a["side"], a["type"], a["answers"]) for a in report["arms"]] == [("left", "ur", False),
                                                                            ("right", "ur", False)]
    assert report["camera"]["type"] == "oak"
    ports = {p["port"] for p in report["serial"]["devices"]}
    assert {"/dev/ttyUSB0", "/dev/ttyUSB1"} <= ports  # the configured gripper ports are probed too
    mock = json.loads(run(capsys, "--config", str(REPO / "configs" / "mock.yaml"), "--json"))
    assert all(a["answers"] and a["detail"] == "simulated" for a in mock["arms"])


@pytest.mark.real_sdk
def test_a_franka_without_fci_does_not_answer():
    pytest.importorskip("franky", reason="franky-control is not installed")
    proc = cli_devices.start_franka_probe("127.0.0.1")
    import time

    ok, detail = cli_devices.finish_franka_probe(proc, time.monotonic() + 20.0, 20.0)
    assert not ok and "NetworkException" in detail
