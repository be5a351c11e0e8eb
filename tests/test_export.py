"""trackdeform export: a session's episodes in the paper's layout and as a LeRobot dataset."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from orchestrator.cli import main
from orchestrator.config import ColorOutputConfig
from orchestrator.recorder import EpisodeWriter
from tdrecord import read_episodes, read_paper_layout, read_reference_npz
from tests.conftest import make_frame

W, H, N = 64, 48, 5
BASES = {"left": np.eye(4), "right": np.eye(4)}
BASES["right"][:3, 3] = [0.0, -0.9, 0.0]
T_WORLD_CAM = np.array([[0.0, 0.0, -1.0, 1.4], [1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.7], [0.0, 0.0, 0.0, 1.0]])


def _keypoints(n: int) -> np.ndarray:
    """(N, 3) m: a straight rope moving along y with the frame number."""
    return np.stack([np.linspace(0.3, 0.7, N), np.full(N, 0.001 * n), np.full(N, 0.2)], axis=1)


def _write_session(folder: Path, frames_per_episode: int = 6) -> list[np.ndarray]:
    """Two 6-frame episodes of one run with arm states and live keypoints; returns each frame's depth."""
    folder.mkdir(parents=True)
    depths = []
    cal = {"width": W, "height": H, "K": make_frame().intrinsics.K.tolist(), "T_world_cam": T_WORLD_CAM.tolist(),
           "T_world_base": {a: T.tolist() for a, T in BASES.items()}, "depth_scale": 0.001}
    run = {"object": "rope", "category": "dlo", "program": "rope_swing", "speed": "medium", "repeat": 0,
           "run_index": 0, "attempt": 1, "plan_pass": 0, "session_started": "2026-01-01T00:00:00Z", "fps": 30,
           "calibration": cal}
    n = 0
    for e in range(2):
        w = EpisodeWriter(folder / f"episode_{e:06d}.mcap", "cam0", color=ColorOutputConfig(codec="raw"))
        for _ in range(frames_per_episode):
            f = make_frame(n, W, H)
            depths.append(f.depth.copy())
            q = [0.01 * n] * 7
            w.write_arm_state({"stamp": f.host_stamp, "u": [0.5, 0.2, 0.3, 0.0, 0.0, 0.1] * 2,
                               "left": {"q": q, "dq": [0.0] * 7, "gripper_width": 0.01, "grasped": True},
                               "right": {"q": q, "dq": [0.0] * 7, "gripper_width": 0.02, "grasped": True}})
            w.write_frame(f, T_WORLD_CAM)
            w.write_keypoints({"schema": "trackdeform.Keypoints/1", "frame_number": n, "stamp": f.device_stamp,
                               "keypoints": _keypoints(n).tolist(), "edges": [[i, i + 1] for i in range(N - 1)],
                               "grasp_indices": {"left": 0, "right": N - 1}, "status": "tracking",
                               "rest_lengths": [0.1] * (N - 1)}, f.host_stamp)
            n += 1
        w.close({**run, "episode_index": e, "chunk_index": e, "complete": True, "fault": False})
    return depths


def test_paper_export_round_trips(tmp_path: Path) -> None:
    session = tmp_path / "session"
    depths = _write_session(session)
    out = tmp_path / "paper"
    assert main(["export", str(session), "--format", "paper", "--out", str(out), "--quiet"]) == 0
    folders = sorted(p for p in out.iterdir() if p.is_dir())
    assert [p.name for p in folders] == ["episode_000000", "episode_000001"]
    seq = read_paper_layout(folders[1])
    frames = list(seq.frames)
    assert len(frames) == 6
    assert all(np.array_equal(f.depth, d) for f, d in zip(frames, depths[6:], strict=True))
    assert np.array_equal(frames[0].color, read_episodes(session / "episode_000001.mcap").frames.iter_from(0)
                          .__next__().color)
    ref = read_reference_npz(folders[1])
    assert ref.keypoints.shape == (6, N, 3) and ref.edges.shape == (N - 1, 2)
    np.testing.assert_allclose(ref.keypoints[2], _keypoints(8), atol=1e-9)  # frame 8 is this episode's third
    assert json.loads((folders[1] / "meta.json").read_text())["keypoints"] == "live"


def test_export_errors_name_the_folder(tmp_path: Path, capsys) -> None:
    assert main(["export", str(tmp_path / "missing"), "--format", "paper", "--out", str(tmp_path / "o")]) == 2
    assert f"{tmp_path / 'missing'}: no such session folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["export", str(tmp_path / "empty"), "--format", "paper", "--out", str(tmp_path / "o")]) == 2
    assert "no finished episode files" in capsys.readouterr().err


@pytest.mark.skipif(importlib.util.find_spec("lerobot") is None,
                    reason="LeRobot is not installed (pip install 'trackdeform3d[lerobot]')")
def test_lerobot_export_opens_in_lerobots_loader(tmp_path: Path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    session = tmp_path / "session"
    depths = _write_session(session)
    out = tmp_path / "lerobot"
    assert main(["export", str(session), "--format", "lerobot", "--out", str(out), "--quiet"]) == 0
    ds = LeRobotDataset("trackdeform/rope", root=out / "rope", video_backend="pyav")
    assert ds.num_episodes == 1 and len(ds) == 12  # one LeRobot episode per program run
    item = ds[8]
    assert np.array_equal(item["observation.depth"].numpy().reshape(H, W), depths[8])  # lossless depth
    state = item["observation.state"].numpy()
    np.testing.assert_allclose(state[: 3 * N].reshape(N, 3), _keypoints(8), atol=1e-6)
    np.testing.assert_allclose(state[3 * N: 3 * N + 7], [0.08] * 7, atol=1e-6)
    assert item["observation.images.color"].shape == (3, H, W)
    assert int(item["trackdeform.episode_file"]) == 1  # frame 8 came from the second 5 s file
    side = json.loads((out / "rope" / "meta" / "trackdeform.json").read_text())
    assert [f["file"] for f in side["episodes"][0]["files"]] == ["episode_000000.mcap", "episode_000001.mcap"]
