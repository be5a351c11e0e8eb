"""Episode files open in Foxglove: Foxglove's own readers and channel parser (../shared/tools/foxglove-check).

The checker is a Node tool kept read-only beside the repo; it is copied to a temporary folder and
installed there with ``npm ci``. Skipped when node / npm or the tool is absent, or npm ci cannot run
(no registry). ``TRACKDEFORM_FOXGLOVE_CHECK`` names another copy of the tool.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from orchestrator.config import ColorOutputConfig, DepthOutputConfig
from orchestrator.recorder import EpisodeWriter
from tests.conftest import REPO, make_frame

TOOL = Path(os.environ.get("TRACKDEFORM_FOXGLOVE_CHECK", REPO.parent / "shared" / "tools" / "foxglove-check"))


@pytest.fixture(scope="module")
def checker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """check.mjs of an installed copy of the tool (module scope: npm ci once)."""
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("node / npm not installed (CI installs nodejs and npm with apt-get)")
    if not (TOOL / "check.mjs").is_file():
        pytest.skip(f"foxglove-check not found at {TOOL} (expected ../shared/tools/foxglove-check beside the repo)")
    dest = tmp_path_factory.mktemp("foxglove-check") / "fxc"
    shutil.copytree(TOOL, dest, ignore=shutil.ignore_patterns("node_modules"))
    for p in dest.rglob("*"):  # the source is read-only; the copy must be writable for npm
        p.chmod(p.stat().st_mode | 0o200)
    dest.chmod(dest.stat().st_mode | 0o200)
    proc = subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=dest, capture_output=True, text=True,
                          timeout=600)
    if proc.returncode != 0:
        pytest.skip(f"npm ci could not install foxglove-check: {proc.stderr.strip()[-400:]}")
    return dest / "check.mjs"


def _check(checker: Path, *paths: Path) -> dict:
    proc = subprocess.run(["node", str(checker), *map(str, paths), "--json"], capture_output=True, text=True,
                          timeout=600)
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert proc.returncode == 0 and report["ok"], proc.stdout[-4000:] + proc.stderr[-2000:]
    return report


@pytest.mark.parametrize("color,depth", [("h264", "png"), ("jpeg", "raw"), ("raw", "png"), ("h264", "planes")])
def test_every_channel_of_a_written_episode_parses(tmp_path: Path, checker: Path, color: str, depth: str) -> None:
    path = tmp_path / "episode_000000.mcap"
    w = EpisodeWriter(path, "cam0", color=ColorOutputConfig(codec=color), depth=DepthOutputConfig(codec=depth))
    tcp = {"left_tcp": np.eye(4), "right_tcp": np.eye(4)}
    for n in range(6):
        w.write_frame(make_frame(n), np.eye(4))
        w.write_arm_state({"stamp": n / 30, "left": {"stamp": n / 30, "q": [0.1] * 7, "dq": [0.0] * 7,
                                                      "gripper_width": 0.05, "grasped": False},
                           "right": {"stamp": n / 30, "q": [0.1] * 7, "dq": [0.0] * 7, "gripper_width": 0.05,
                                     "grasped": True}, "u": [0.0] * 11 + [float("nan")]}, tcp)
    kp = np.array([[0.1, 0.2, 0.3], [0.2, 0.2, 0.3], [np.nan, 0.1, 0.1]])
    w.write_keypoints({"schema": "trackdeform.Keypoints/1", "frame_number": 2, "stamp": 2 / 30,
                       "keypoints": kp.tolist(), "edges": [[0, 1], [1, 2]], "grasp_indices": {"left": 0, "right": -1},
                       "object": "rope", "category": "dlo", "status": "tracking", "abs_mm": 1.0, "cd_mm": None,
                       "anchors": [0]}, 2 / 30)
    w.write_keypoints({"frame_number": 3, "stamp": 0.1, "keypoints": [], "edges": [], "status": "lost"}, 0.1)
    w.close({"object": "rope"})
    report = _check(checker, path)
    channels = {c["topic"]: c for c in report["files"][0]["channels"]}
    for topic in ("/arms/state", "/cam/cam0/frame_info", "/keypoints", "/keypoints/scene", "/cam/cam0/color",
                  "/cam/cam0/depth"):
        assert channels[topic]["decoded"] == channels[topic]["count"] > 0, channels[topic]


@pytest.mark.slow
def test_sim_time_demo_episodes_pass(checker: Path, demo_final_resumed: tuple[Path, str]) -> None:
    """The shared simulated-time demo (live keypoints, then final ones written into every episode) opens."""
    out = demo_final_resumed[0]
    files = sorted(out.glob("episode_*.mcap"))
    assert files
    report = _check(checker, *files)
    assert len(report["files"]) == len(files)
    for f in report["files"]:  # the final keypoints (tracked after each run) parse, one per frame
        channels = {c["topic"]: c for c in f["channels"]}
        final = channels["/keypoints/final"]
        assert final["decoded"] == final["count"] == channels["/cam/cam0/color"]["count"], final
