"""``trackdeform router``: the daemon-side and the subscriber-side clients exchange data through it only."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

from orchestrator.bus import Bus
from orchestrator.config import BusConfig
from tests.conftest import REPO


def test_router_relays_between_clients_and_stops_on_sigterm(port: int) -> None:
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "orchestrator.cli", "router", "--listen", endpoint],
                            cwd=REPO, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stderr is not None
        assert "listening on" in proc.stderr.readline()
        client = BusConfig(mode="client", listen=[], connect=[endpoint])
        with Bus(client, "t", listen=False) as daemon, Bus(client, "t", listen=False) as watcher:
            key = daemon.key("keypoints")
            sub = watcher.subscribe(key, ring=16)
            got, deadline = None, time.monotonic() + 10
            while got is None and time.monotonic() < deadline:
                daemon.put(key, b"kp")
                time.sleep(0.05)
                got = sub.try_recv()
            assert got is not None and got.payload.to_bytes() == b"kp"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_router_refuses_tls_without_certificate(port: int) -> None:
    out = subprocess.run([sys.executable, "-m", "orchestrator.cli", "router", "--listen", f"tls/127.0.0.1:{port}"],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "tls/ listen endpoint needs bus.tls.certificate" in out.stderr
