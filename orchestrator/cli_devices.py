"""``trackdeform devices``: what a station can see, so a new station's config can be written.

Lists RealSense and OAK cameras through the SDKs' own discovery (serial / device id, name,
firmware), serial ports (pyserial's ``list_ports`` plus the configured and ``--port`` ones)
with a Robotiq gripper answering a Modbus status read on them (read only: nothing is written,
the fingers do not move), and, given ``--config``, whether each configured arm's controller
answers (a UR's dashboard greeting, a Franka FCI connection through franky) and whether the
configured camera is among those found. A missing SDK is reported with the extra that
installs it; nothing found is not an error.
"""

from __future__ import annotations

import argparse
import json
import socket
import time
from pathlib import Path
from typing import Any

from drivers.base import DeviceError
from drivers.franka import INSTALL_HINT as FRANKA_HINT
from drivers.oak import INSTALL_HINT as OAK_HINT
from drivers.realsense import INSTALL_HINT as REALSENSE_HINT
from drivers.serial_gripper import INSTALL_HINT as SERIAL_HINT
from drivers.ur import INSTALL_HINT as UR_HINT

EXTRA_HINT = {"realsense": REALSENSE_HINT, "oak": OAK_HINT, "serial": SERIAL_HINT, "franka": FRANKA_HINT,
              "ur": UR_HINT}
ARM_SDK = {"franka": "franky", "ur": "rtde_control"}
ROBOTIQ_BAUDRATE = 115200
ROBOTIQ_SLAVE_ID = 9


def _missing(kind: str, module: str) -> dict[str, Any]:
    return {"available": False, "module": module, "install": EXTRA_HINT[kind], "devices": []}


def list_realsense() -> dict[str, Any]:
    """RealSense devices through ``rs.context().query_devices()``: serial, name, firmware, USB type."""
    try:
        import pyrealsense2 as rs
    except ImportError:
        return _missing("realsense", "pyrealsense2")
    out: dict[str, Any] = {"available": True, "module": "pyrealsense2", "version": getattr(rs, "__version__", "?"),
                           "devices": []}
    fields = {"serial": "serial_number", "name": "name", "firmware": "firmware_version",
              "recommended_firmware": "recommended_firmware_version", "usb": "usb_type_descriptor",
              "port": "physical_port"}
    try:
        for dev in rs.context().query_devices():
            info = {}
            for key, attr in fields.items():
                ci = getattr(rs.camera_info, attr, None)
                if ci is not None and dev.supports(ci):
                    info[key] = dev.get_info(ci)
            out["devices"].append(info)
    except RuntimeError as exc:
        out["error"] = str(exc)
    return out


def list_oak(open_devices: bool = True) -> dict[str, Any]:
    """OAK devices through ``dai.Device.getAllAvailableDevices()``; opened briefly for name and bootloader.

    An OAK runs the firmware its depthai library ships, so that version is its firmware.
    """
    try:
        import depthai as dai
    except ImportError:
        return _missing("oak", "depthai")
    version = getattr(dai, "__version__", "?")
    out: dict[str, Any] = {"available": True, "module": "depthai", "version": version, "devices": []}
    try:
        infos = dai.Device.getAllAvailableDevices()
    except RuntimeError as exc:
        out["error"] = str(exc)
        return out
    for info in infos:
        entry: dict[str, Any] = {"device_id": info.getDeviceId(), "name": info.name,
                                 "state": str(info.state).split(".")[-1], "protocol": str(info.protocol).split(".")[-1],
                                 "firmware": f"depthai {version}"}
        if open_devices:
            try:
                with dai.Device(info) as device:
                    entry["product"] = device.getProductName()
                    boot = device.getBootloaderVersion()
                    entry["bootloader"] = str(boot) if boot is not None else None
            except RuntimeError as exc:  # e.g. in use by another process
                entry["error"] = str(exc)
        out["devices"].append(entry)
    return out


def probe_robotiq(port: str, baudrate: int = ROBOTIQ_BAUDRATE, slave_id: int = ROBOTIQ_SLAVE_ID,
                  timeout: float = 0.2) -> dict[str, Any]:
    """A Modbus status read of a Robotiq gripper on ``port`` (nothing written): its status, or why not."""
    from drivers.config import SerialGripperConfig
    from drivers.serial_gripper import SerialGripper

    g = SerialGripper(SerialGripperConfig(port=port, baudrate=baudrate, slave_id=slave_id, timeout=timeout,
                                          retries=0), name=port)
    try:
        status = g.probe()
    except DeviceError as exc:
        return {"answers": False, "slave_id": slave_id, "baudrate": baudrate, "detail": str(exc)}
    return {"answers": True, "slave_id": slave_id, "baudrate": baudrate, "status": status,
            "activated": bool(status["gACT"] and status["gSTA"] == 3)}


def list_serial(extra_ports: list[tuple[str, int, int]], timeout: float) -> dict[str, Any]:
    """Serial ports from pyserial's list_ports plus ``extra_ports`` ((path, baudrate, slave id)), each probed."""
    try:
        from serial.tools import list_ports
    except ImportError:
        return _missing("serial", "pyserial")
    import serial

    out: dict[str, Any] = {"available": True, "module": "pyserial", "version": getattr(serial, "__version__", "?"),
                           "devices": []}
    seen: dict[str, dict[str, Any]] = {}
    for p in list_ports.comports():
        seen[p.device] = {"port": p.device, "description": p.description, "hwid": p.hwid,
                          "serial": p.serial_number, "probe": (ROBOTIQ_BAUDRATE, ROBOTIQ_SLAVE_ID)}
    for path, baud, slave in extra_ports:
        entry = seen.setdefault(path, {"port": path, "description": "configured", "hwid": None, "serial": None})
        entry["probe"] = (baud, slave)
    for entry in seen.values():
        baud, slave = entry.pop("probe")
        entry["robotiq"] = probe_robotiq(entry["port"], baud, slave, timeout)
        out["devices"].append(entry)
    return out


UR_DASHBOARD_PORT = 29999
UR_GREETING = "Connected: Universal Robots Dashboard Server"


def probe_ur(host: str, timeout: float, port: int = UR_DASHBOARD_PORT) -> tuple[bool, str]:
    """(answers, detail): a UR controller greets every client of its dashboard server with one line.

    Read only (no command is sent). An open TCP port alone proves nothing (a proxy or another
    service may accept it); the greeting does.
    """
    try:
        with socket.create_connection((host, port), timeout=timeout) as s:
            s.settimeout(timeout)
            data = b""
            deadline = time.monotonic() + timeout
            while b"\n" not in data and time.monotonic() < deadline:
                chunk = s.recv(256)
                if not chunk:
                    break
                data += chunk
    except OSError as exc:
        return False, f"dashboard server {host}:{port}: {exc}"
    line = data.split(b"\n", 1)[0].decode("utf-8", "replace").strip()
    if line.startswith(UR_GREETING):
        return True, f"dashboard server: {line!r}"
    return False, f"dashboard server {host}:{port} sent {line!r}, not the UR greeting"


FRANKA_PROBE = """
import sys
import franky
kwargs = {"realtime_config": franky.RealtimeConfig.Ignore} if hasattr(franky, "RealtimeConfig") else {}
try:
    franky.Robot(sys.argv[1], **kwargs)
except Exception as exc:
    print(f"{type(exc).__name__}: {exc}")
    sys.exit(1)
"""
FRANKY_IMPORT_S = 5.0  # allowance for the probe process to import franky


def start_franka_probe(host: str) -> Any:
    """A child process that connects a franky Robot to ``host``'s FCI (no motion) and exits 0 on success.

    A child, not a thread: libfranka's connect cannot be interrupted, and franky must not
    share a process with pylibfranka.
    """
    import subprocess
    import sys

    return subprocess.Popen([sys.executable, "-c", FRANKA_PROBE, host], stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True)


def finish_franka_probe(proc: Any, deadline: float, timeout: float) -> tuple[bool, str]:
    """(answers, detail) of a probe started by :func:`start_franka_probe`; killed at ``deadline``."""
    import subprocess

    try:
        out, _ = proc.communicate(timeout=max(deadline - time.monotonic(), 0.0))
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        return False, f"FCI: no answer within {timeout:.1f} s"
    if proc.returncode == 0:
        return True, "FCI connection accepted"
    return False, f"FCI: {out.strip() or f'probe exited with {proc.returncode}'}"


def check_arms(station: Any, timeout: float) -> list[dict[str, Any]]:
    """Each configured arm: does its controller answer (fake arms always do), is its SDK installed."""
    import importlib.util

    rows, franka = [], []
    for side in ("left", "right"):
        arm = getattr(station, side).arm
        row: dict[str, Any] = {"side": side, "type": arm.type, "host": getattr(arm, "host", None)}
        if arm.type in ARM_SDK and importlib.util.find_spec(ARM_SDK[arm.type]) is None:
            row["install"] = EXTRA_HINT[arm.type]
        if arm.type == "ur":
            row["answers"], row["detail"] = probe_ur(arm.host, timeout)
        elif arm.type == "franka" and "install" in row:
            row["answers"], row["detail"] = False, "not checked: franky is not installed"
        elif arm.type == "franka":
            franka.append((row, start_franka_probe(arm.host)))  # both arms' probes run at once
        else:
            row["answers"], row["detail"] = True, "simulated"
        rows.append(row)
    deadline = time.monotonic() + timeout + FRANKY_IMPORT_S
    for row, proc in franka:
        row["answers"], row["detail"] = finish_franka_probe(proc, deadline, timeout + FRANKY_IMPORT_S)
    return rows


def _configured_ports(station: Any) -> list[tuple[str, int, int]]:
    ports = []
    for side in ("left", "right"):
        g = getattr(station, side).gripper
        if g.type == "serial":
            ports.append((g.port, g.baudrate, g.slave_id))
    return ports


def _camera_check(station: Any, report: dict[str, Any]) -> dict[str, Any] | None:
    cam = station.camera
    if cam.type == "realsense":
        found = [d.get("serial") for d in report["realsense"]["devices"]]
        want = cam.serial
    elif cam.type == "oak":
        found = [d.get("device_id") for d in report["oak"]["devices"]] + [d.get("name") for d in
                                                                          report["oak"]["devices"]]
        want = cam.device_id
    else:
        return None
    return {"type": cam.type, "id": cam.id, "wanted": want,
            "found": (want in found) if want else bool([f for f in found if f])}


def collect(config_path: str | None = None, ports: list[str] | None = None, timeout: float = 1.0,
            open_oak: bool = True) -> dict[str, Any]:
    """The whole report as a JSON-ready dict."""
    station = None
    if config_path:
        from orchestrator.config import load_config

        station = load_config(Path(config_path)).station
    extra = [(p, ROBOTIQ_BAUDRATE, ROBOTIQ_SLAVE_ID) for p in ports or []]
    if station is not None:
        extra += _configured_ports(station)
    report: dict[str, Any] = {
        "realsense": list_realsense(),
        "oak": list_oak(open_devices=open_oak),
        "serial": list_serial(extra, timeout=min(timeout, 0.5)),
    }
    if station is not None:
        report["config"] = str(config_path)
        report["arms"] = check_arms(station, timeout)
        report["camera"] = _camera_check(station, report)
    return report


def format_report(report: dict[str, Any]) -> str:
    """The report as the text the command prints."""
    lines = []

    def section(title: str, part: dict[str, Any], fmt: Any) -> None:
        if not part["available"]:
            lines.append(f"{title}: {part['module']} is not installed: {part['install']}")
            return
        lines.append(f"{title} ({part['module']} {part.get('version', '?')}):")
        if part.get("error"):
            lines.append(f"  discovery failed: {part['error']}")
        if not part["devices"]:
            lines.append("  none found")
        lines.extend(f"  {fmt(d)}" for d in part["devices"])

    section("RealSense cameras", report["realsense"],
            lambda d: f"serial {d.get('serial', '?')}  {d.get('name', '')}  firmware {d.get('firmware', '?')}"
                      + (f"  USB {d['usb']}" if d.get("usb") else ""))
    section("OAK cameras", report["oak"],
            lambda d: f"device_id {d['device_id']}  {d.get('product') or d.get('name', '')}  state {d['state']}  "
                      f"firmware {d['firmware']}" + (f"  bootloader {d['bootloader']}" if d.get("bootloader") else "")
                      + (f"  ({d['error']})" if d.get("error") else ""))

    def fmt_port(d: dict[str, Any]) -> str:
        r = d["robotiq"]
        if r["answers"]:
            st = r["status"]
            what = (f"Robotiq gripper (slave {r['slave_id']} @ {r['baudrate']} baud): "
                    f"{'activated' if r['activated'] else 'not activated'}, gPO {st['gPO']}, fault 0x{st['gFLT']:02X}")
        else:
            what = "no Robotiq gripper answering"
        return f"{d['port']}  {d.get('description') or ''}: {what}"

    section("Serial ports", report["serial"], fmt_port)
    if "arms" in report:
        lines.append(f"Arms in {report['config']}:")
        for a in report["arms"]:
            host = f" {a['host']}" if a.get("host") else ""
            state = "answers" if a["answers"] else "does not answer"
            hint = f"; driver needs: {a['install']}" if a.get("install") else ""
            lines.append(f"  {a['side']:5s} {a['type']}{host}: {state} ({a['detail']}){hint}")
        cam = report.get("camera")
        if cam is not None:
            want = cam["wanted"] or "(first device)"
            lines.append(f"Camera {cam['id']} ({cam['type']} {want}): {'found' if cam['found'] else 'not found'}")
    return "\n".join(lines)


def cmd_devices(args: argparse.Namespace) -> int:
    """Print (or --json) what this station can see."""
    report = collect(args.config, args.port, timeout=args.timeout)
    if args.json:
        print(json.dumps(report, indent=2, default=str))
    else:
        print(format_report(report))
    return 0


def register(sub: Any) -> None:
    """Add the ``devices`` subcommand to the CLI's subparsers."""
    p = sub.add_parser("devices", help="list the cameras, grippers and arms this station can see")
    p.add_argument("--config", help="station YAML: also check each configured arm, gripper port and camera")
    p.add_argument("--port", action="append", help="also probe this serial port for a Robotiq gripper (repeatable)")
    p.add_argument("--timeout", type=float, default=1.0, help="per-probe timeout, s (default 1)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.set_defaults(func=cmd_devices)

