"""Robotiq 2F-85-style parallel gripper over Modbus RTU (pyserial).

The gripper exposes three output registers (action request, position, speed/force) at
0x03E8, written with function 0x10, and three input registers (status, fault, position,
current) at 0x07D0, read with function 0x04. Every frame carries a CRC-16/Modbus that we
compute and check here; a timed-out or corrupted reply is retried ``retries`` times before
a :class:`~drivers.base.DeviceError`. Widths are metres, forces newtons, speeds m/s. A
finger position maps linearly between ``open_position`` (gPO fully open: the manual's example
reads 13, the fingers' software limit, not 0) and ``closed_position`` (gPO fully closed);
speed and force registers map linearly over the configured ranges. A status is trusted only
once its position request echo (gPR) equals the last command's position: before that its
gOBJ still describes the previous command.
"""

from __future__ import annotations

import threading
from typing import Any

from drivers.base import DeviceError, DriverUnavailable
from drivers.clock import Clock, RealClock
from drivers.config import SerialGripperConfig
from tdcommon.types import GripperState

ACTION_REGISTER = 0x03E8
STATUS_REGISTER = 0x07D0
WRITE_MULTIPLE = 0x10
READ_INPUT = 0x04

# action request byte (register 0x03E8, high byte)
R_ACT = 0x01  # activate
R_GTO = 0x08  # go to the requested position
# gripper status byte (register 0x07D0, high byte)
G_ACT = 0x01
G_STA_SHIFT = 4  # 2 bits: 0 reset, 1 activating, 3 activation complete
G_OBJ_SHIFT = 6  # 2 bits: 0 moving, 1 object while opening, 2 object while closing, 3 at position
OBJ_MOVING, OBJ_OPENING_CONTACT, OBJ_CLOSING_CONTACT, OBJ_AT_POSITION = 0, 1, 2, 3

INSTALL_HINT = "pip install pyserial  (or: pip install 'trackdeform3d')"


def _build_crc_table() -> tuple[int, ...]:
    """The 256-entry table of CRC-16/Modbus (reflected polynomial 0xA001)."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _build_crc_table()


def crc16_modbus(data: bytes) -> int:
    """CRC-16/Modbus of ``data`` (init 0xFFFF, reflected poly 0xA001); sent low byte first."""
    crc = 0xFFFF
    for b in data:
        crc = (crc >> 8) ^ _CRC_TABLE[(crc ^ b) & 0xFF]
    return crc


def with_crc(frame: bytes) -> bytes:
    """``frame`` followed by its CRC, low byte first, as Modbus RTU puts it on the wire."""
    crc = crc16_modbus(frame)
    return bytes(frame) + bytes((crc & 0xFF, crc >> 8))


def check_crc(frame: bytes) -> bool:
    """True when the last two bytes of ``frame`` are the CRC of the rest."""
    return len(frame) >= 3 and crc16_modbus(frame[:-2]) == frame[-2] | (frame[-1] << 8)


class ModbusError(Exception):
    """A reply that cannot be used: timeout, bad CRC or malformed (retried by the caller)."""


class SerialGripper:
    """A Robotiq 2F-85-style gripper on a serial Modbus RTU line."""

    def __init__(self, config: SerialGripperConfig, *, name: str = "gripper", clock: Clock | None = None,
                 **_: Any) -> None:
        self.config = config
        self.name = name
        self._clock: Clock = clock or RealClock()
        self._port: Any = None
        self._lock = threading.Lock()
        self._serial_exc: tuple[type[BaseException], ...] = (OSError,)
        self._last_state: GripperState | None = None
        self._expected_pr: int | None = None  # position of the last command, until gPR echoes it
        self.requests = 0  # Modbus transactions sent (for health reporting)
        self.retried = 0  # transactions that needed a retry

    # ------------------------------------------------------------------ unit mapping
    def width_to_register(self, width: float) -> int:
        """Opening width (m) -> position request on the calibrated open..closed gPO range."""
        c = self.config
        w = min(max(width, 0.0), c.stroke)
        return int(round(c.open_position + (1.0 - w / c.stroke) * (c.closed_position - c.open_position)))

    def register_to_width(self, value: int) -> float:
        """Position register (gPO) -> opening width (m), clamped to [0, stroke]."""
        c = self.config
        a = (value - c.open_position) / (c.closed_position - c.open_position)
        return (1.0 - min(max(a, 0.0), 1.0)) * c.stroke

    def speed_to_register(self, speed: float) -> int:
        """Finger speed (m/s) -> speed register, clamped to the gripper's range."""
        c = self.config
        a = (speed - c.min_speed) / max(c.max_speed - c.min_speed, 1e-9)
        return int(round(min(max(a, 0.0), 1.0) * 255))

    def force_to_register(self, force: float) -> int:
        """Grip force (N) -> force register, clamped to the gripper's range."""
        c = self.config
        a = (force - c.min_force) / max(c.max_force - c.min_force, 1e-9)
        return int(round(min(max(a, 0.0), 1.0) * 255))

    # ------------------------------------------------------------------ lifecycle
    def connect(self) -> None:
        """Open the port and run the activation sequence (reset, activate, wait for gSTA = 3)."""
        self.open_port()
        self.activate()

    def probe(self) -> dict[str, int]:
        """Open the port, read the status registers once and close it; nothing is written, nothing moves.

        Raises DeviceError when the port cannot be opened or no gripper answers (for discovery).
        """
        self.open_port()
        try:
            return self.read_status(raise_fault=False)
        finally:
            self.close()

    def open_port(self) -> None:
        """Open the serial port with the configured line settings (8N1) without talking to the gripper."""
        try:
            import serial  # lazy: only stations with a serial gripper need it
        except ImportError as exc:
            raise DriverUnavailable(f"serial gripper needs pyserial: {INSTALL_HINT}") from exc
        self._serial_exc = (serial.SerialException, OSError)
        try:
            self._port = serial.Serial(
                port=self.config.port,
                baudrate=self.config.baudrate,
                bytesize=8,
                parity="N",
                stopbits=1,
                timeout=self.config.timeout,
            )
        except self._serial_exc as exc:
            raise DeviceError(f"{self.name}: cannot open {self.config.port}: {exc}") from exc

    def activate(self) -> None:
        """Reset then activate the gripper and wait until activation completes."""
        self.write_action(0, 0, 0, 0)
        self.write_action(R_ACT, 0, 0, 0)
        deadline = self._clock.now() + self.config.activation_timeout
        while True:
            status = self.read_status()
            if status["gACT"] and status["gSTA"] == 3:
                return
            if self._clock.now() >= deadline:
                raise DeviceError(f"{self.name}: activation did not complete (status {status})")
            self._clock.sleep_until(self._clock.now() + 0.05)

    def close(self) -> None:
        """Close the serial port (idempotent); the fingers keep their last command."""
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except self._serial_exc:
                pass

    # ------------------------------------------------------------------ commands
    def command(self, closed: bool, width: float | None = None, force: float | None = None) -> None:
        """Start grasping (position 255 with ``force`` N) or opening (to ``width`` m, or fully: position 0).

        Full open/close ask for 0/255 and the fingers stop at their software limits.
        """
        if closed:
            position = 255 if width is None else self.width_to_register(width)
        else:
            position = 0 if width is None else self.width_to_register(width)
        self._last_state = None  # the next read_state must see the new command
        self._expected_pr = position
        self.write_action(
            R_ACT | R_GTO,
            position,
            self.speed_to_register(self.config.speed),
            self.force_to_register(self.config.force if force is None else force),
        )

    def read_state(self) -> GripperState:
        """Width from the finger position, grasped from gOBJ; a read younger than state_period is reused.

        The state poller asks at the joint-state rate (100+ Hz); the RS-485 line needs a few ms
        per transaction, so reads are rate-limited to leave room for commands.
        """
        last = self._last_state
        if last is not None and self._clock.now() - last.stamp < self.config.state_period:
            return last
        status = self.read_status()
        width = self.register_to_width(status["gPO"])
        if self._expected_pr is not None and status["gPR"] != self._expected_pr:
            # not yet the new command's status: gPO is live, gOBJ still the old command's
            return GripperState(self._clock.now(), width, False)
        self._expected_pr = None
        grasped = status["gOBJ"] in (OBJ_OPENING_CONTACT, OBJ_CLOSING_CONTACT)
        self._last_state = GripperState(self._clock.now(), width, grasped)
        return self._last_state

    @property
    def command_acknowledged(self) -> bool:
        """True once a status read showed the last command's position echoed in gPR."""
        return self._expected_pr is None

    def read_status(self, *, raise_fault: bool = True) -> dict[str, int]:
        """The decoded input registers (gACT, gGTO, gSTA, gOBJ, gFLT, gPR, gPO, gCU).

        A major fault (gFLT >= 0x0A) raises DeviceError unless ``raise_fault`` is False.
        """
        reply = self._transact(
            bytes((self.config.slave_id, READ_INPUT))
            + STATUS_REGISTER.to_bytes(2, "big")
            + (3).to_bytes(2, "big"),
            expected=READ_INPUT,
        )
        if reply[2] != 6:
            raise DeviceError(f"{self.name}: status reply has {reply[2]} data bytes, expected 6")
        b = reply[3:9]
        status = {
            "gACT": b[0] & G_ACT,
            "gGTO": (b[0] >> 3) & 1,
            "gSTA": (b[0] >> G_STA_SHIFT) & 3,
            "gOBJ": (b[0] >> G_OBJ_SHIFT) & 3,
            "gFLT": b[2] & 0x0F,
            "gPR": b[3],
            "gPO": b[4],
            "gCU": b[5],
        }
        if raise_fault and status["gFLT"] >= 0x0A:  # 0x0A and above are major faults that need a reactivation
            raise DeviceError(f"{self.name}: gripper fault 0x{status['gFLT']:02X}", recoverable=True)
        return status

    def write_action(self, action: int, position: int, speed: int, force: int) -> None:
        """Write the six action-request bytes (action, 0, 0, position, speed, force)."""
        payload = bytes((action, 0, 0, position, speed, force))
        self._transact(
            bytes((self.config.slave_id, WRITE_MULTIPLE))
            + ACTION_REGISTER.to_bytes(2, "big")
            + (3).to_bytes(2, "big")
            + bytes((len(payload),))
            + payload,
            expected=WRITE_MULTIPLE,
        )

    def recover(self) -> None:
        """Reopen the port if needed and reactivate (clears faults)."""
        if self._port is None:
            self.connect()
        else:
            self.activate()

    # ------------------------------------------------------------------ Modbus RTU
    def _transact(self, request: bytes, *, expected: int) -> bytes:
        """Send ``request`` (without CRC) and return the checked reply, retrying bad ones."""
        if self._port is None:
            raise DeviceError(f"{self.name}: not connected")
        frame = with_crc(request)
        last: Exception | None = None
        with self._lock:
            for attempt in range(self.config.retries + 1):
                self.requests += 1
                if attempt:
                    self.retried += 1
                try:
                    self._port.reset_input_buffer()
                    self._port.write(frame)
                    return self._read_reply(expected)
                except ModbusError as exc:
                    last = exc
                except self._serial_exc as exc:
                    raise DeviceError(f"{self.name}: serial port failed: {exc}") from exc
        raise DeviceError(
            f"{self.name}: no valid reply after {self.config.retries + 1} attempts: {last}", recoverable=True
        )

    def _read_reply(self, expected: int) -> bytes:
        """Read one reply frame for function ``expected``; raise ModbusError when unusable."""
        head = self._port.read(2)
        if len(head) < 2:
            raise ModbusError("timeout")
        if head[0] != self.config.slave_id:
            raise ModbusError(f"reply from slave {head[0]}, expected {self.config.slave_id}")
        if head[1] == expected | 0x80:
            rest = self._port.read(3)
            frame = head + rest
            if len(frame) < 5 or not check_crc(frame):
                raise ModbusError("corrupted exception reply")
            raise DeviceError(f"{self.name}: Modbus exception code {frame[2]}", recoverable=False)
        if head[1] != expected:
            raise ModbusError(f"reply function 0x{head[1]:02X}, expected 0x{expected:02X}")
        if expected == READ_INPUT:
            count = self._port.read(1)
            if len(count) < 1:
                raise ModbusError("timeout")
            rest = self._port.read(count[0] + 2)
            frame = head + count + rest
            want = 3 + count[0] + 2
        else:
            rest = self._port.read(6)
            frame = head + rest
            want = 8
        if len(frame) < want:
            raise ModbusError("timeout")
        if not check_crc(frame):
            raise ModbusError("CRC mismatch")
        return frame
