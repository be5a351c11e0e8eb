"""Shared fixtures: free loopback ports, frames, repo paths."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from orchestrator.bus import free_port
from tdcommon.types import CameraIntrinsics, RGBDFrame

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def port() -> int:
    return free_port()


def make_frame(n: int = 0, w: int = 64, h: int = 48, seed: int = 0) -> RGBDFrame:
    """A small synthetic RGB-D frame with frame number ``n``."""
    rng = np.random.default_rng(seed + n)
    color = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    depth = rng.integers(300, 2000, (h, w)).astype(np.uint16)
    return RGBDFrame(color, depth, 0.001, CameraIntrinsics.from_fov(w, h, 69.0), n / 30.0, n / 30.0 + 0.01, n)
