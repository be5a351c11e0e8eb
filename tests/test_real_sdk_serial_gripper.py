"""SerialGripper through the real pyserial on a pty pair, against a Modbus RTU responder written here.

The responder follows the Robotiq 2F-85 manual's register map: function 0x10 writes the three
action-request registers at 0x03E8 (rACT, rGTO; position, speed, force), function 0x04 reads
the three status registers at 0x07D0 (gACT, gGTO, gSTA, gOBJ; fault, position request echo
gPR; position gPO, current gCU). The fingers stop at software limits (gPO 13 open, 226
closed), gPR echoes a command one poll late, a request with a bad CRC gets no reply, an
unknown function or address an exception reply. Faults can be queued per reply: corrupted
CRC, split into delayed pieces, silence, or an exception.
"""

from __future__ import annotations

import os
import pty
import select
import threading
import time
import tty
from collections import deque

import pytest

from drivers.base import DeviceError
from drivers.config import SerialGripperConfig
from drivers.serial_gripper import SerialGripper, check_crc, with_crc

serial = pytest.importorskip("serial", reason="pyserial is not installed (pip install pyserial)")
pytestmark = pytest.mark.real_sdk

SLAVE = 0x09
OPEN_LIMIT, CLOSED_LIMIT = 13, 226
STEP = 70  # gPO counts the fingers move per status poll


class RobotiqResponder(threading.Thread):
    """A Modbus RTU slave on the master side of a pty, answering as a Robotiq 2F-85."""

    def __init__(self, fd: int, object_at: int | None = None) -> None:
        super().__init__(daemon=True)
        self.fd = fd
        self.object_at = object_at
        self.action = bytearray(6)
        self.echo = 0
        self.echo_wait = 0
        self.position = OPEN_LIMIT
        self.sta = 0
        self.obj = 0
        self.faults: deque[str] = deque()  # "crc", "split", "silent", "exception" for upcoming replies
        self.requests: list[bytes] = []
        self.bad_requests = 0
        self.replies: list[bytes] = []
        self._halt = threading.Event()
        self._buf = bytearray()

    # ------------------------------------------------------------------ wire
    def run(self) -> None:
        while not self._halt.is_set():
            ready, _, _ = select.select([self.fd], [], [], 0.02)
            if not ready:
                continue
            try:
                self._buf += os.read(self.fd, 256)
            except OSError:
                return
            while (frame := self._take_frame()) is not None:
                self._answer(frame)

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=2.0)

    def _take_frame(self) -> bytes | None:
        """One complete request frame off the buffer, by its function code's length."""
        b = self._buf
        if len(b) < 2:
            return None
        if b[1] == 0x10:
            if len(b) < 7:
                return None
            n = 7 + b[6] + 2
        else:
            n = 8
        if len(b) < n:
            return None
        frame = bytes(b[:n])
        del b[:n]
        return frame

    def _send(self, reply: bytes) -> None:
        fault = self.faults.popleft() if self.faults else "ok"
        if fault == "silent":
            return
        if fault == "exception":
            reply = with_crc(bytes((SLAVE, reply[1] | 0x80, 0x04)))  # slave device failure
        if fault == "crc":
            reply = reply[:-1] + bytes((reply[-1] ^ 0xA5,))
        self.replies.append(reply)
        if fault == "split":
            for i in range(0, len(reply), 3):
                os.write(self.fd, reply[i:i + 3])
                time.sleep(0.004)
        else:
            os.write(self.fd, reply)

    # ------------------------------------------------------------------ register map
    def _answer(self, frame: bytes) -> None:
        self.requests.append(frame)
        if not check_crc(frame) or frame[0] != SLAVE:
            self.bad_requests += 1  # a Modbus slave ignores a frame with a bad CRC
            return
        func, addr = frame[1], int.from_bytes(frame[2:4], "big")
        if func == 0x10:
            count = int.from_bytes(frame[4:6], "big")
            if addr != 0x03E8 or count != 3 or frame[6] != 6:
                self._send(with_crc(bytes((SLAVE, 0x90, 0x02))))  # illegal data address
                return
            self._write_action(frame[7:13])
            self._send(with_crc(frame[:6]))
        elif func == 0x04:
            count = int.from_bytes(frame[4:6], "big")
            if addr != 0x07D0 or not 1 <= count <= 3:
                self._send(with_crc(bytes((SLAVE, 0x84, 0x02))))
                return
            self._poll()
            data = self._status()[: 2 * count]
            self._send(with_crc(bytes((SLAVE, 0x04, len(data))) + data))
        else:
            self._send(with_crc(bytes((SLAVE, func | 0x80, 0x01))))  # illegal function

    def _write_action(self, payload: bytes) -> None:
        if not payload[0] & 0x01:
            self.sta, self.obj = 0, 0  # reset
        elif not self.action[0] & 0x01:
            self.sta = 1  # activating
        self.action[:] = payload
        self.echo_wait = 1

    def _poll(self) -> None:
        """One status poll: activation completes, gPR catches up, the fingers move a step."""
        if self.action[0] & 0x01 and self.sta == 1:
            self.sta = 3
            return
        if self.echo_wait:
            self.echo_wait -= 1
            return
        self.echo = self.action[3]
        if self.sta != 3 or not self.action[0] & 0x08:
            return
        target = min(max(self.echo, OPEN_LIMIT), CLOSED_LIMIT)
        closing = target > self.position
        stop = target
        if self.object_at is not None and closing and self.position <= self.object_at < target:
            stop = self.object_at
        move = max(-STEP, min(STEP, stop - self.position))
        self.position += move
        if self.position != stop:
            self.obj = 0
        elif stop != target:
            self.obj = 2  # object detected while closing
        else:
            self.obj = 3  # at the requested position

    def _status(self) -> bytes:
        act, gto = self.action[0] & 0x01, (self.action[0] >> 3) & 1
        status = act | (gto << 3) | (self.sta << 4) | (self.obj << 6)
        return bytes((status, 0x00, 0x00, self.echo, self.position, 0x00))


@pytest.fixture
def line():
    """(responder, slave device path) of a raw pty pair; both ends closed afterwards."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    responder = RobotiqResponder(master)
    responder.start()
    yield responder, os.ttyname(slave)
    responder.stop()
    os.close(master)
    os.close(slave)


def gripper(path: str, **kw) -> SerialGripper:
    kw.setdefault("timeout", 0.1)
    kw.setdefault("state_period", 0.0)
    return SerialGripper(SerialGripperConfig(port=path, **kw), name="left")


def settle(g: SerialGripper, polls: int = 12) -> None:
    for _ in range(polls):
        g.read_state()


def test_activation_open_and_the_manuals_status_frame(line):
    responder, path = line
    g = gripper(path)
    g.connect()
    assert responder.requests[0] == bytes.fromhex("091003E8000306000000000000") + bytes.fromhex("7330")
    assert responder.sta == 3
    g.command(closed=False)
    settle(g)
    # the manual's "opening is completed" reply, byte for byte: gOBJ 3, gPR 0, gPO 13/255
    assert responder.replies[-1] == bytes.fromhex("090406" + "F900" + "0000" + "0D00" + "17AA")
    st = g.read_state()
    assert st.width == pytest.approx(0.085) and not st.grasped and g.command_acknowledged
    g.close()
    assert responder.bad_requests == 0


def test_grasp_reports_the_calibrated_width_only_after_the_echo(line):
    responder, path = line
    responder.object_at = 120
    g = gripper(path)
    g.connect()
    g.command(closed=False)
    settle(g)
    g.command(closed=True, force=60.0)
    first = g.read_state()  # gPR still 0: the old "at position" must not be trusted
    assert not g.command_acknowledged and not first.grasped
    settle(g)
    st = g.read_state()
    assert st.grasped and responder.position == 120
    assert st.width == pytest.approx(0.085 * (CLOSED_LIMIT - 120) / (CLOSED_LIMIT - OPEN_LIMIT))
    g.close()


def test_crc_errors_and_silence_are_retried_then_a_device_error(line):
    responder, path = line
    g = gripper(path, retries=2)
    g.connect()
    responder.faults.extend(["crc", "silent"])
    g.read_state()
    assert g.retried == 2
    responder.faults.extend(["crc"] * 3)
    with pytest.raises(DeviceError, match="no valid reply after 3 attempts") as info:
        g.read_state()
    assert info.value.recoverable
    g.recover()  # reactivation once the line is clean
    g.close()


def test_split_replies_are_reassembled(line):
    responder, path = line
    g = gripper(path, timeout=1.0)  # the pieces come 4 ms apart; a loaded machine must not turn them into a retry
    responder.faults.extend(["split"] * 40)
    g.connect()
    g.command(closed=False)
    settle(g)
    assert g.read_state().width == pytest.approx(0.085)
    assert g.retried == 0
    g.close()


def test_exception_reply_is_a_non_recoverable_device_error(line):
    responder, path = line
    g = gripper(path)
    g.connect()
    responder.faults.append("exception")
    with pytest.raises(DeviceError, match="Modbus exception code 4") as info:
        g.command(closed=True)
    assert not info.value.recoverable
    g.close()


def test_unopenable_port_is_a_device_error(tmp_path):
    g = gripper(str(tmp_path / "ttyUSB9"))
    with pytest.raises(DeviceError, match="cannot open"):
        g.connect()
