"""Fake ur-rtde modules (``rtde_control``, ``rtde_receive``, ``dashboard_client``) over a simulated arm.

Signatures follow ur-rtde's Python bindings: ``RTDEControlInterface(hostname)``,
``servoJ(q, speed, acceleration, time, lookahead_time, gain)`` (positional), ``servoStop(a)``,
``initPeriod()``/``waitPeriod(t_start)``, ``isConnected``/``reconnect``/``reuploadScript``/
``isProgramRunning``; ``RTDEReceiveInterface(hostname)`` with ``getActualQ``/``getActualQd``/
``isProtectiveStopped``/``isEmergencyStopped``; ``DashboardClient(hostname)`` with ``connect``/
``closeSafetyPopup``/``unlockProtectiveStop``/``disconnect``.
"""

from __future__ import annotations

import datetime
import time
import types
from typing import Any

import numpy as np


class SimUR:
    """One simulated UR controller: joint state, safety state, script state, fault injection."""

    def __init__(self, q0: np.ndarray | None = None) -> None:
        self.q = np.zeros(6) if q0 is None else np.asarray(q0, dtype=float)[:6].copy()
        self.qd = np.zeros(6)
        self.protective_stop_after: int | None = None  # servoJ calls before a protective stop
        self.protective = False
        self.emergency = False
        self.script_running = True
        self.connected = True
        self.servo_calls: list[tuple[float, list[float], float, float, float, float, float]] = []
        self.calls: list[str] = []

    def servo(self, q: list[float], speed: float, acc: float, dt: float, lookahead: float, gain: float) -> bool:
        if not self.connected or not self.script_running:
            raise RuntimeError("RTDE control script is not running!")
        self.servo_calls.append((time.monotonic(), list(q), speed, acc, dt, lookahead, gain))
        if self.protective_stop_after is not None and len(self.servo_calls) > self.protective_stop_after:
            self.protective_stop_after = None
            self.protective = True
            self.script_running = False
            self.qd[:] = 0.0
            return False
        self.q = np.asarray(q, dtype=float)
        return True


SIMS: dict[str, SimUR] = {}

# Names a double offers that the real ur-rtde does not: the simulated controller and bookkeeping.
DOUBLE_ONLY = {"SimUR", "SIMS", "sim_for", "make_modules", "DOUBLE_ONLY"}


def sim_for(host: str) -> SimUR:
    return SIMS.setdefault(host, SimUR())


class RTDEControlInterface:
    DOUBLE_ONLY = {"sim", "frequency", "period"}

    def __init__(self, hostname: str, frequency: float = -1.0, flags: int = 0, ur_cap_port: int = 50002,
                 rt_priority: int = 0) -> None:
        self.sim = sim_for(hostname)
        if not self.sim.connected:
            raise RuntimeError(f"Failed to connect to {hostname}")
        self.frequency = 500.0 if frequency < 0 else frequency  # e-series default
        self.period = 1.0 / self.frequency  # waitPeriod paces at the interface frequency
        self.sim.calls.append(f"control.__init__({self.frequency:g})")

    def servoJ(self, q: list[float], speed: float, acceleration: float, time_: float, lookahead_time: float,  # noqa: N802
               gain: float, /) -> bool:
        assert len(q) == 6
        return self.sim.servo(q, speed, acceleration, time_, lookahead_time, gain)

    def servoStop(self, a: float = 10.0) -> bool:  # noqa: N802
        self.sim.calls.append(f"servoStop({a})")
        return True

    def initPeriod(self) -> datetime.timedelta:  # noqa: N802 - ur-rtde returns a steady-clock timedelta
        return datetime.timedelta(seconds=time.monotonic())

    def waitPeriod(self, t_start: datetime.timedelta) -> None:  # noqa: N802
        assert isinstance(t_start, datetime.timedelta), "waitPeriod takes initPeriod()'s timedelta"
        rest = t_start.total_seconds() + self.period - time.monotonic()
        if rest > 0:
            time.sleep(rest)

    def isConnected(self) -> bool:  # noqa: N802
        return self.sim.connected

    def reconnect(self) -> bool:
        self.sim.calls.append("control.reconnect")
        self.sim.connected = True
        return True

    def isProgramRunning(self) -> bool:  # noqa: N802
        return self.sim.script_running

    def reuploadScript(self) -> bool:  # noqa: N802
        self.sim.calls.append("reuploadScript")
        if self.sim.protective:
            raise RuntimeError("cannot upload the script while protective stopped")
        self.sim.script_running = True
        return True

    def stopScript(self) -> None:  # noqa: N802
        self.sim.calls.append("stopScript")
        self.sim.script_running = False

    def disconnect(self) -> None:
        self.sim.calls.append("control.disconnect")


class RTDEReceiveInterface:
    DOUBLE_ONLY = {"sim", "reconnected"}

    def __init__(self, hostname: str, frequency: float = -1.0, variables: Any = None, verbose: bool = False,
                 use_upper_range_registers: bool = False, rt_priority: int = 0) -> None:
        self.sim = sim_for(hostname)
        self.reconnected = False
        if not self.sim.connected:
            raise RuntimeError(f"Failed to connect to {hostname}")

    def getActualQ(self) -> list[float]:  # noqa: N802
        return self.sim.q.tolist()

    def getActualQd(self) -> list[float]:  # noqa: N802
        return self.sim.qd.tolist()

    def isProtectiveStopped(self) -> bool:  # noqa: N802
        return self.sim.protective

    def isEmergencyStopped(self) -> bool:  # noqa: N802
        return self.sim.emergency

    def isConnected(self) -> bool:  # noqa: N802
        return self.sim.connected or self.reconnected

    def reconnect(self) -> bool:
        self.reconnected = True  # its own socket is back; the control link stays down until reconnected
        return True

    def disconnect(self) -> None:
        pass


class DashboardClient:
    DOUBLE_ONLY = {"sim"}

    def __init__(self, hostname: str, port: int = 29999, verbose: bool = False) -> None:
        self.sim = sim_for(hostname)

    def connect(self, timeout_ms: int = 2000) -> None:
        self.sim.calls.append("dashboard.connect")

    def closeSafetyPopup(self) -> None:  # noqa: N802
        self.sim.calls.append("closeSafetyPopup")

    def unlockProtectiveStop(self) -> None:  # noqa: N802
        self.sim.calls.append("unlockProtectiveStop")
        self.sim.protective = False

    def disconnect(self) -> None:
        pass


def make_modules() -> dict[str, types.ModuleType]:
    """Fresh fake modules keyed by import name (simulated controllers reset)."""
    SIMS.clear()
    mods = {name: types.ModuleType(name) for name in ("rtde_control", "rtde_receive", "dashboard_client")}
    mods["rtde_control"].RTDEControlInterface = RTDEControlInterface
    mods["rtde_receive"].RTDEReceiveInterface = RTDEReceiveInterface
    mods["dashboard_client"].DashboardClient = DashboardClient
    return mods
