"""Shared fixtures: free loopback ports, frames, repo paths, mock config variants and a shared demo session."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

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


def mock_yaml(path: Path, overrides: dict[str, Any]) -> Path:
    """configs/mock.yaml with dotted ``overrides`` (e.g. ``{"tracking.live_init.enabled": False}``) set, written
    to ``path``: a config file for CLI tests that need the demo with one setting changed."""
    data = yaml.safe_load((REPO / "configs" / "mock.yaml").read_text())
    for dotted, value in overrides.items():
        node = data
        *parents, leaf = dotted.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


NO_LIVE_INIT = {"tracking.live_init.enabled": False}


def cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """``trackdeform ARGS`` in a child process from the repository root; output captured as text."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}  # for worker processes too (retrack's, Ray's)
    return subprocess.run([sys.executable, "-m", "orchestrator.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, env=env)


@pytest.fixture(scope="session")
def demo_10s(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10 s simulated-time rope demo without live tracking: one program run, two 5 s episodes. Shared by the
    tests that read a recorded session; a test that writes into it works on ``copy_session`` of it."""
    out = tmp_path_factory.mktemp("demo10") / "demo"
    r = cli("demo", "--sim-time", "--seconds", "10", "--out", str(out), "--port", str(free_port()), "--no-tracking")
    assert r.returncode == 0, r.stderr[-3000:]
    return out


@pytest.fixture(scope="session")
def demo_10s_track(demo_10s: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """``trackdeform track`` of the shared 10 s demo (it only reads the session): the output folder (the reference
    layout's 3d_keypoints.npz and 3d_keypoints_raw.npz) and the printed metrics."""
    import json

    out = tmp_path_factory.mktemp("demo10track")
    r = cli("track", str(demo_10s), "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr[-3000:]
    return out, json.loads(r.stdout)


def copy_session(src: Path, dst: Path) -> Path:
    """A private copy of a recorded session folder at ``dst``."""
    shutil.copytree(src, dst)
    return dst
