"""Universal Robots arm through ur-rtde: servoJ streaming of the timed joint samples.

A background thread resamples the :class:`~tdcommon.types.JointMotion` at ``servo_rate`` Hz
and sends each sample with ``servoJ(q, speed, acceleration, dt, lookahead_time, gain)``,
paced by ur-rtde's ``initPeriod()``/``waitPeriod()``; it holds the final sample for one
lookahead so the arm settles, then ``servoStop()``. UR arms have six joints: the first six
program columns are used and the reported state carries 0.0 as the seventh joint. A
protective stop or a lost connection becomes a :class:`~drivers.base.DeviceError`;
``recover()`` unlocks the protective stop (dashboard server), reconnects and re-uploads the
control script. ur-rtde is imported lazily.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from drivers.base import DeviceError, DriverUnavailable
from drivers.clock import Clock, RealClock
from drivers.config import URArmConfig
from tdcommon.types import JointMotion, JointState

INSTALL_HINT = "pip install 'trackdeform3d[ur]'"
UR_DOF = 6
SERVO_SPEED = 0.5  # servoJ's speed/acceleration arguments are unused by the UR controller
SERVO_ACCEL = 0.5
SERVO_STOP_DECEL = 2.0  # rad/s^2 for servoStop


def import_rtde() -> tuple[Any, Any]:
    """Import ur-rtde's control and receive modules or raise DriverUnavailable."""
    try:
        import rtde_control  # lazy: only UR stations need ur-rtde
        import rtde_receive
    except ImportError as exc:
        raise DriverUnavailable(f"the UR driver needs ur-rtde: {INSTALL_HINT}") from exc
    return rtde_control, rtde_receive


def import_dashboard() -> Any:
    """Import ur-rtde's dashboard client (used to unlock protective stops)."""
    try:
        import dashboard_client
    except ImportError as exc:
        raise DriverUnavailable(f"the UR driver needs ur-rtde: {INSTALL_HINT}") from exc
    return dashboard_client


def _pad7(v: Any) -> np.ndarray:
    """A 6-vector from the robot as the (7,) joint vector of the JointState contract."""
    out = np.zeros(7)
    a = np.asarray(v, dtype=np.float64).reshape(-1)[:7]
    out[: len(a)] = a
    return out


class URArm:
    """A UR e-series / CB3 arm streaming servoJ set-points from a background thread."""

    def __init__(self, config: URArmConfig, *, name: str = "ur", clock: Clock | None = None, **_: Any) -> None:
        self.config = config
        self.name = name
        self.host = config.host
        self._clock: Clock = clock or RealClock()
        self._ctrl: Any = None
        self._recv: Any = None
        self._thread: threading.Thread | None = None
        self._abort = threading.Event()
        self._done = threading.Event()
        self._done.set()
        self._error: DeviceError | None = None
        self.sent = 0  # servoJ set-points sent in the current motion
        self.overruns = 0  # cycles that exceeded the servo period (health)

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        """Open the RTDE receive and control interfaces (the latter uploads the control script)."""
        rtde_control, rtde_receive = import_rtde()
        try:
            self._recv = rtde_receive.RTDEReceiveInterface(self.host)
            # waitPeriod() paces at the interface frequency, so it must be the servo rate
            self._ctrl = rtde_control.RTDEControlInterface(self.host, frequency=self.config.servo_rate)
        except RuntimeError as exc:
            raise DeviceError(f"{self.name}: cannot connect to {self.host}: {exc}") from exc
        self._check_safety()
        self.read_state()

    def close(self) -> None:
        """Stop streaming, stop the control script and disconnect (idempotent)."""
        if self._ctrl is None and self._recv is None:
            return
        self.stop()
        for iface, extra in ((self._ctrl, "stopScript"), (self._recv, None)):
            if iface is None:
                continue
            try:
                if extra:
                    getattr(iface, extra)()
                iface.disconnect()
            except RuntimeError:
                pass
        self._ctrl = self._recv = None

    # ------------------------------------------------------------------ state
    def read_state(self) -> JointState:
        """Actual joint positions/velocities (6 joints, 7th reported as 0)."""
        if self._recv is None:
            raise DeviceError(f"{self.name}: not connected")
        try:
            q, dq = self._recv.getActualQ(), self._recv.getActualQd()
        except RuntimeError as exc:
            raise DeviceError(f"{self.name}: read state: {exc}") from exc
        if len(q) < UR_DOF:
            raise DeviceError(f"{self.name}: no joint data received (connection lost?)")
        return JointState(self._clock.now(), _pad7(q), _pad7(dq))

    def _check_safety(self) -> None:
        """Raise DeviceError when the arm is protective- or emergency-stopped."""
        try:
            emergency, protective = self._recv.isEmergencyStopped(), self._recv.isProtectiveStopped()
        except RuntimeError as exc:
            raise DeviceError(f"{self.name}: safety status: {exc}") from exc
        if emergency:
            raise DeviceError(f"{self.name}: emergency stop is pressed", recoverable=False)
        if protective:
            raise DeviceError(f"{self.name}: protective stop", recoverable=True)

    # ------------------------------------------------------------------ motion
    def start_motion(self, motion: JointMotion) -> None:
        """Start the servoJ streaming thread (returns at once); the motion must start here."""
        if self._ctrl is None:
            raise DeviceError(f"{self.name}: not connected")
        if not self._done.is_set():
            raise DeviceError(f"{self.name}: a motion is already running")
        self._check_safety()
        current = self.read_state().q[:UR_DOF]
        gap = float(np.max(np.abs(np.asarray(motion.q[0], dtype=np.float64)[:UR_DOF] - current)))
        if gap > self.config.start_tolerance:
            raise DeviceError(f"{self.name}: motion starts {gap:.3f} rad from the current joint state")
        self._abort.clear()
        self._done.clear()
        self._error = None
        self.sent = 0
        self._thread = threading.Thread(target=self._stream, args=(motion,), name=f"{self.name}-servoJ",
                                        daemon=True)
        self._thread.start()

    def _stream(self, motion: JointMotion) -> None:
        """Send the resampled set-points at servo_rate with servoJ, then hold, then servoStop."""
        ctrl, recv, cfg = self._ctrl, self._recv, self.config
        dt = 1.0 / cfg.servo_rate
        duration = motion.duration
        steps = int(math.ceil(duration / dt - 1e-9)) + 1
        hold = int(math.ceil(cfg.lookahead_time / dt))
        try:
            for k in range(steps + hold):
                if self._abort.is_set():
                    break
                t_start = ctrl.initPeriod()
                q, _ = motion.sample(min(k * dt, duration))
                ok = ctrl.servoJ(q[:UR_DOF].tolist(), SERVO_SPEED, SERVO_ACCEL, dt, cfg.lookahead_time, cfg.gain)
                self.sent += 1
                if not ok or recv.isProtectiveStopped() or recv.isEmergencyStopped():
                    self._check_safety()
                    raise DeviceError(f"{self.name}: servoJ refused at t={k * dt:.3f} s")
                ctrl.waitPeriod(t_start)
        except DeviceError as exc:
            self._error = exc
        except RuntimeError as exc:  # ur-rtde raises RuntimeError when the script/connection is gone
            try:
                self._check_safety()
                self._error = DeviceError(f"{self.name}: servoJ failed: {exc}")
            except DeviceError as safety:
                self._error = safety
        finally:
            try:
                ctrl.servoStop(SERVO_STOP_DECEL)
            except RuntimeError:
                pass
            self._done.set()

    def wait_motion(self, timeout: float) -> bool:
        """Wait for the streaming thread; re-raise its DeviceError."""
        done = self._done.wait(max(timeout, 0.0))
        if done and self._error is not None:
            err, self._error = self._error, None
            raise err
        return done

    def stop(self) -> None:
        """Abort streaming; the thread's servoStop decelerates the arm."""
        self._abort.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        self._error = None

    def recover(self) -> None:
        """Unlock a protective stop, reconnect what dropped and re-upload the control script."""
        if self._recv is None or self._ctrl is None:
            self.connect()
            return
        self.stop()
        try:
            if not self._recv.isConnected():
                self._recv.reconnect()
            if self._recv.isEmergencyStopped():
                raise DeviceError(f"{self.name}: emergency stop is pressed", recoverable=False)
            if self._recv.isProtectiveStopped():
                dash = import_dashboard().DashboardClient(self.host)
                dash.connect()
                try:
                    dash.closeSafetyPopup()
                    dash.unlockProtectiveStop()  # the controller refuses this within 5 s of the stop
                finally:
                    dash.disconnect()
            if not self._ctrl.isConnected():
                self._ctrl.reconnect()
            if not self._ctrl.isProgramRunning():
                self._ctrl.reuploadScript()
        except DeviceError:
            raise
        except RuntimeError as exc:
            raise DeviceError(f"{self.name}: recover: {exc}", recoverable=True) from exc
        self._check_safety()
