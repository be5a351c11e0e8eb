"""Shared fixtures: free loopback ports, frames, repo paths."""

from __future__ import annotations

import socket
from pathlib import Path

import numpy as np
import pytest

from tdcommon.types import CameraIntrinsics, RGBDFrame

REPO = Path(__file__).resolve().parent.parent


def free_port() -> int:
    """A TCP port on 127.0.0.1 that the OS just handed out (so two test runs do not share one)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def port() -> int:
    return free_port()


def make_frame(n: int = 0, w: int = 64, h: int = 48, seed: int = 0) -> RGBDFrame:
    """A small synthetic RGB-D frame with frame number ``n``."""
    rng = np.random.default_rng(seed + n)
    color = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    depth = rng.integers(300, 2000, (h, w)).astype(np.uint16)
    return RGBDFrame(color, depth, 0.001, CameraIntrinsics.from_fov(w, h, 69.0), n / 30.0, n / 30.0 + 0.01, n)
