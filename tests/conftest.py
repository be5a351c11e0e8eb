"""Shared fixtures: free loopback ports, frames, repo paths, mock config variants and a shared demo session."""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
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


def built_once(tmp_path_factory: pytest.TempPathFactory, name: str, build: Callable[[Path], None]) -> Path:
    """The folder ``name`` that ``build(folder)`` fills, built once per test run and shared by the pytest-xdist
    workers (each worker has its own session fixtures): the first worker to ask builds it under a lock, the
    others wait and reuse it. Users must only read it (``copy_session`` to write)."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, shared by its workers
    folder, done = root / "shared" / name, root / "shared" / f"{name}.done"
    folder.parent.mkdir(parents=True, exist_ok=True)
    with open(root / "shared" / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)  # a build that failed in another worker
            folder.mkdir()
            build(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def demo_10s(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10 s simulated-time rope demo without live tracking: one program run, two 5 s episodes. Shared by the
    tests that read a recorded session; a test that writes into it works on ``copy_session`` of it."""

    def build(folder: Path) -> None:
        r = cli("demo", "--sim-time", "--seconds", "10", "--out", str(folder / "demo"), "--port", str(free_port()),
                "--no-tracking")
        assert r.returncode == 0, r.stderr[-3000:]

    return built_once(tmp_path_factory, "demo10", build) / "demo"


@pytest.fixture(scope="session")
def demo_10s_track(demo_10s: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, Any]]:
    """``trackdeform track`` of the shared 10 s demo (it only reads the session): the output folder (the reference
    layout's 3d_keypoints.npz and 3d_keypoints_raw.npz) and the printed metrics."""
    import json

    def build(folder: Path) -> None:
        r = cli("track", str(demo_10s), "--out", str(folder), "--json")
        assert r.returncode == 0, r.stderr[-3000:]
        (folder / "metrics.json").write_text(r.stdout)

    out = built_once(tmp_path_factory, "demo10track", build)
    return out, json.loads((out / "metrics.json").read_text())


@pytest.fixture(scope="session")
def demo_final_resumed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A 5 s simulated-time rope demo recorded with final tracking off, then resumed with it on (live tracking
    initialised on the run, not before it): the session folder and the second demo's output. Every episode of it
    ends with live and final keypoints. Shared; read only."""

    def build(folder: Path) -> None:
        out = folder / "demo"
        base = ["demo", "--sim-time", "--seconds", "5", "--out", str(out), "--port", str(free_port())]
        off = mock_yaml(folder / "mock_nofinal.yaml", {**NO_LIVE_INIT, "tracking.final": False})
        first = cli(*base, "--config", str(off))
        assert first.returncode == 0, first.stderr[-3000:]
        from tdrecord import load_episode

        assert all(load_episode(p, images=False).keypoints_final is None for p in out.glob("episode_*.mcap"))
        second = cli(*base, "--config", str(mock_yaml(folder / "mock_final.yaml", NO_LIVE_INIT)), timeout=900)
        assert second.returncode == 0, second.stderr[-3000:]
        (folder / "second_stdout.txt").write_text(second.stdout)

    folder = built_once(tmp_path_factory, "demo_final_resumed", build)
    return folder / "demo", (folder / "second_stdout.txt").read_text()


def copy_session(src: Path, dst: Path) -> Path:
    """A private copy of a recorded session folder at ``dst``."""
    shutil.copytree(src, dst)
    return dst
