"""zenoh on loopback: a subscriber in another process receives frames (explicit endpoints, no multicast)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time

import numpy as np

from orchestrator.bus import Bus, local_endpoints
from orchestrator.config import BusConfig
from tdcommon.wire import encode_frame
from tests.conftest import REPO, make_frame


def test_subscriber_in_another_process_receives_frames(port: int) -> None:
    bus_cfg = BusConfig(listen=[f"tcp/127.0.0.1:{port}"])
    sub_script = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(REPO)!r})
        from orchestrator.bus import Bus
        from orchestrator.config import BusConfig
        from tdcommon.wire import decode_frame
        bus = Bus(BusConfig(listen=[]), "t", listen=False, connect=["tcp/127.0.0.1:{port}"])
        sub = bus.subscribe(bus.key("cam", "cam0", "frame"), ring=4)
        print("ready", flush=True)
        got, deadline = [], time.monotonic() + 20
        while len(got) < 3 and time.monotonic() < deadline:
            s = sub.try_recv()
            if s is None:
                time.sleep(0.005)
                continue
            got.append(decode_frame(s.payload.to_bytes()).frame.frame_number)
        print("got", *got, flush=True)
        bus.close()
    """)
    with Bus(bus_cfg, "t") as bus:
        proc = subprocess.Popen([sys.executable, "-c", sub_script], stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == "ready"
            key = bus.key("cam", "cam0", "frame")
            deadline = time.monotonic() + 20
            n = 0
            while proc.poll() is None and time.monotonic() < deadline:
                bus.put(key, encode_frame(make_frame(n), np.eye(4), "cam0"))
                n += 1
                time.sleep(0.05)
            out = proc.communicate(timeout=20)[0]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    numbers = [int(x) for x in out.split("got")[1].split()]
    assert len(numbers) == 3 and numbers == sorted(numbers)


def test_local_endpoints() -> None:
    assert local_endpoints(["tcp/0.0.0.0:7447", "tcp/10.0.0.2:1"]) == ["tcp/127.0.0.1:7447", "tcp/10.0.0.2:1"]
