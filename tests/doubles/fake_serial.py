"""A fake ``serial`` module whose port simulates a Robotiq 2F-85 answering Modbus RTU frames."""

from __future__ import annotations

import types
from collections import deque

from drivers.serial_gripper import check_crc, with_crc

# Names a double offers that the real pyserial does not.
DOUBLE_ONLY = {"RobotiqSim", "FakePort", "make_module", "DOUBLE_ONLY", "check_crc", "with_crc", "ports"}


class SerialException(OSError):
    """Stand-in for ``serial.SerialException``."""


class RobotiqSim:
    """The gripper's register model: activation, finger motion towards the request, object contact."""

    def __init__(self, slave_id: int = 9, object_at: int | None = None, activation_polls: int = 2,
                 open_limit: int = 13, closed_limit: int = 226, echo_polls: int = 0) -> None:
        self.slave_id = slave_id
        self.object_at = object_at  # position register where fingers meet an object (None: no object)
        self.activation_polls = activation_polls
        self.open_limit, self.closed_limit = open_limit, closed_limit  # the fingers' software limits (gPO)
        self.echo_polls = echo_polls  # status reads after a command before gPR echoes it (old gOBJ meanwhile)
        self.echo = 0
        self.echo_wait = 0
        self.action = bytes(6)
        self.position = 0
        self.activating = 0
        self.activated = False
        self.writes: list[bytes] = []  # action payloads, in order
        self.reads = 0

    def handle(self, frame: bytes) -> bytes:
        """Reply to one request frame (with CRC) as the gripper would."""
        assert check_crc(frame), f"driver sent a bad CRC: {frame.hex()}"
        slave, func = frame[0], frame[1]
        assert slave == self.slave_id
        if func == 0x10:
            addr = int.from_bytes(frame[2:4], "big")
            if addr != 0x03E8:
                return with_crc(bytes((slave, 0x90, 0x02)))
            payload = frame[7:13]
            self.writes.append(payload)
            if payload[0] & 0x01 and not self.action[0] & 0x01:
                self.activating = self.activation_polls
            if not payload[0] & 0x01:
                self.activated = False
            self.echo_wait = self.echo_polls
            self.action = payload
            return with_crc(frame[:6])
        if func == 0x04:
            self.reads += 1
            self._step()
            return with_crc(bytes((slave, 0x04, 6)) + self.status_bytes())
        return with_crc(bytes((slave, func | 0x80, 0x01)))

    def _step(self) -> None:
        """Advance the simulation by one poll: finish activation, move the fingers."""
        if self.action[0] & 0x01 and not self.activated:
            self.activating -= 1
            if self.activating <= 0:
                self.activated = True
        if self.echo_wait > 0:
            self.echo_wait -= 1
            return
        self.echo = self.action[3]
        if self.activated and self.action[0] & 0x08:
            target = min(max(self.action[3], self.open_limit), self.closed_limit)
            if self.object_at is not None and target > self.object_at >= self.position:
                target = self.object_at
            self.position = target

    def status_bytes(self) -> bytes:
        """The six input-register bytes."""
        act = self.action[0] & 0x01
        sta = 3 if self.activated else (1 if act else 0)
        gto = (self.action[0] >> 3) & 1
        obj = 0
        if self.activated and gto:
            contact = self.object_at is not None and self.echo > self.object_at == self.position
            obj = 2 if contact else 3
        status = act | (gto << 3) | (sta << 4) | (obj << 6)
        return bytes((status, 0, 0, self.echo, self.position, 10))


class FakePort:
    """A serial port whose peer is a :class:`RobotiqSim`; faults can be queued per request."""

    DOUBLE_ONLY = {"sim", "kwargs", "rx", "faults", "sent"}

    def __init__(self, sim: RobotiqSim, **kwargs: object) -> None:
        self.sim = sim
        self.kwargs = kwargs
        self.rx = bytearray()
        self.faults: deque[str] = deque()  # "crc", "timeout" or "ok" for upcoming requests
        self.sent: list[bytes] = []
        self.closed = False

    def reset_input_buffer(self) -> None:
        self.rx.clear()

    def write(self, data: bytes) -> int:
        self.sent.append(bytes(data))
        reply = self.sim.handle(bytes(data))
        fault = self.faults.popleft() if self.faults else "ok"
        if fault == "timeout":
            return len(data)
        if fault == "crc":
            reply = reply[:-1] + bytes(((reply[-1] ^ 0x5A) & 0xFF,))
        self.rx += reply
        return len(data)

    def read(self, n: int) -> bytes:
        out = bytes(self.rx[:n])
        del self.rx[:n]
        return out

    def close(self) -> None:
        self.closed = True


def make_module(sim: RobotiqSim) -> types.ModuleType:
    """A ``serial`` module whose ``Serial(...)`` opens a :class:`FakePort` on ``sim``."""
    mod = types.ModuleType("serial")
    mod.SerialException = SerialException
    mod.ports: list[FakePort] = []

    def Serial(**kwargs: object) -> FakePort:  # noqa: N802 - pyserial's name
        port = FakePort(sim, **kwargs)
        mod.ports.append(port)
        return port

    mod.Serial = Serial
    return mod
