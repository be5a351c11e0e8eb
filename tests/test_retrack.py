"""``trackdeform retrack``: 2 local workers, Ray on a local cluster and ``trackdeform track`` agree; resuming;
the version folder's checks; the report's version table."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from orchestrator.config import DEFAULT_CONFIG, load_config
from orchestrator.retrack import (
    JOURNAL_FILE,
    RetrackError,
    concat_sequences,
    mean_distance_mm,
    npz_complete,
    open_version,
    read_progress_journal,
    read_version,
    run_done,
    session_runs,
)
from tdrecord import FrameSource, Sequence, read_reference_npz
from tests.conftest import REPO, cli, copy_session, make_frame

TOL_M = 1e-6
HAVE_RAY = importlib.util.find_spec("ray") is not None


_cli = cli


def _version_arrays(session: Path, version: str) -> dict[str, np.ndarray]:
    """The version's per-episode files of a one-run session, concatenated in episode order."""
    files = sorted((session / "keypoints" / version).glob("episode_*.npz"))
    assert [f.stem for f in files] == [f.stem for f in sorted(session.glob("episode_*.mcap"))]
    parts = [np.load(f) for f in files]
    return {k: np.concatenate([p[k] for p in parts]) for k in ("frame_numbers", "keypoints", "raw", "grasp_indices")}


@pytest.fixture(scope="module")
def tracked(tmp_path_factory: pytest.TempPathFactory, demo_10s: Path,
            demo_10s_track: tuple[Path, dict]) -> tuple[Path, dict[str, np.ndarray]]:
    """A copy of the shared 10 s demo (one program run, 2 episodes, no live tracking) and its `trackdeform track`
    keypoints (final = the reference npz's, raw)."""
    session = copy_session(demo_10s, tmp_path_factory.mktemp("retrack") / "demo")
    track = demo_10s_track[0]
    final = read_reference_npz(track / "3d_keypoints.npz").keypoints  # m
    raw = np.load(track / "3d_keypoints_raw.npz")["raw"]
    return session, {"keypoints": final, "raw": raw}


def _assert_same(got: dict[str, np.ndarray], want: dict[str, np.ndarray]) -> None:
    for k in ("keypoints", "raw"):
        assert got[k].shape == want[k].shape, k
        assert np.isfinite(got[k]).all(), k
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=TOL_M, err_msg=k)


@pytest.mark.slow
@pytest.mark.skipif(not HAVE_RAY, reason="ray is not installed (pip install 'trackdeform3d[cluster]')")
def test_ray_on_a_local_cluster_gives_the_keypoints_of_track(tracked) -> None:
    session, want = tracked
    r = _cli("retrack", str(session), "--ray-address", "local", "--workers", "2", "--version", "ray", "--json")
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads(r.stdout)["backend"] == "ray"
    _assert_same(_version_arrays(session, "ray"), want)


@pytest.mark.slow
def test_a_killed_retrack_continues_where_it_stopped_with_the_keypoints_of_track(tracked) -> None:
    """Killed mid-run, then resumed with 2 local workers: the keypoints of ``trackdeform track``; a rerun of the
    complete version rewrites nothing; a torn result file makes its run not done."""
    session, want = tracked
    folder = session / "keypoints" / "killed"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, "-m", "orchestrator.cli", "retrack", str(session), "--workers", "1",
                             "--version", "killed"], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and proc.poll() is None:  # until the first progress line with frames
            line = proc.stderr.readline()
            if "retrack [" in line and not line.split("retrack [")[1].split("]")[1].lstrip().startswith("0/"):
                break
        assert proc.poll() is None, "retrack ended before it could be killed"
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the command and its worker processes
        proc.wait(timeout=30)
        proc.stderr.close()
    assert not list(folder.glob("*.npz")), "a run was written before the kill"

    r = _cli("retrack", str(session), "--workers", "2", "--version", "killed", "--json")
    assert r.returncode == 0, r.stderr[-3000:]
    figures = json.loads(r.stdout)
    assert figures["tracked"] == 1 and figures["frames"] == len(want["raw"]) and not figures["failed"]
    got = _version_arrays(session, "killed")
    _assert_same(got, want)
    assert got["grasp_indices"].shape == (len(want["raw"]), 2)
    info = json.loads((folder / "version.json").read_text())
    assert info["tracking"]["final_window"] == 5 and info["software"]["package"]
    runs = [x for x in read_progress_journal(folder / JOURNAL_FILE) if x["type"] == "run"]
    assert [x["outcome"] for x in runs] == ["done"] and runs[0]["params"]["n_keypoints_1d"] == 20
    # the raw streams are untouched: only the keypoints folder was added
    assert {p.name for p in session.iterdir()} >= {"episode_000000.mcap", "episode_000001.mcap", "keypoints"}

    # a rerun skips the complete run and rewrites nothing
    stamps = {f: f.stat().st_mtime_ns for f in folder.glob("*.npz")}
    r = _cli("retrack", str(session), "--version", "killed", "--json")
    assert r.returncode == 0 and json.loads(r.stdout)["already_done"] == 1, r.stderr[-2000:]
    assert stamps == {f: f.stat().st_mtime_ns for f in stamps}

    # a torn result file (e.g. a disk filled up) makes its run not done: retrack tracks it again (as above)
    (task,) = session_runs(session, load_config(DEFAULT_CONFIG).tracking)
    assert run_done(folder, task)
    torn = folder / "episode_000001.npz"
    torn.write_bytes(torn.read_bytes()[:1000])
    assert not npz_complete(torn, session / torn.with_suffix(".mcap").name) and not run_done(folder, task)


@pytest.mark.slow
def test_the_report_shows_the_versions(tracked, tmp_path: Path) -> None:
    session, _ = tracked
    versions = session / "keypoints"  # the other tests' versions, when they ran first in this process
    names = sorted(p.name for p in versions.iterdir()) if versions.is_dir() else []
    if not names:
        _cli("retrack", str(session), "--workers", "1", "--version", "only", "--json")
        names = ["only"]
    r = _cli("report", str(session), "--out", str(tmp_path / "r"), "--thumbnails", "1", "--track-missing")
    assert r.returncode == 0, r.stderr[-3000:]
    html = (tmp_path / "r" / "report.html").read_text()
    table = html.split('id="versions"')[1].split("</table>")[0]
    for n in names:
        assert f">{n}<" in table
    # the report tracked the run offline like retrack: the versions' raw keypoints are the same (0.000 mm)
    assert "0.000 (" in table


def test_open_version_refuses_other_settings_and_bad_names(tmp_path: Path) -> None:
    cfg = load_config(DEFAULT_CONFIG)
    tracking = cfg.tracking.model_dump(mode="json")
    sw = {"package": "0.1.0", "git": "abc123"}
    folder = open_version(tmp_path, "v1", tracking, sw)
    assert json.loads((folder / "version.json").read_text())["tracking"] == tracking
    assert open_version(tmp_path, "v1", tracking, sw) == folder  # same settings: resumed
    with pytest.raises(RetrackError, match="another tracking"):
        open_version(tmp_path, "v1", {**tracking, "solver_iterations": 7}, sw)
    with pytest.raises(RetrackError, match="another software"):
        open_version(tmp_path, "v1", tracking, {"package": "0.1.0", "git": "def456"})
    for bad in ("../x", "a/b", "", ".hidden"):
        with pytest.raises(RetrackError, match="--version"):
            open_version(tmp_path, bad, tracking, sw)


def test_npz_complete_checks_keys_shapes_and_the_episode(tmp_path: Path) -> None:
    episode = tmp_path / "episode_000000.mcap"
    episode.write_bytes(b"x" * 100)
    good = {"frame_numbers": np.arange(4), "keypoints": np.zeros((4, 3, 3)), "raw": np.zeros((4, 3, 3)),
            "edges": np.array([[0, 1], [1, 2]]), "rest_lengths": np.ones(2), "grasp_indices": np.zeros((4, 2), int),
            "episode_bytes": np.int64(100)}
    path = tmp_path / "episode_000000.npz"
    np.savez(path, **good)
    assert npz_complete(path, episode)
    np.savez(path, **{**good, "episode_bytes": np.int64(99)})  # the episode changed since (recovered)
    assert not npz_complete(path, episode)
    np.savez(path, **{k: v for k, v in good.items() if k != "raw"})
    assert not npz_complete(path, episode)
    np.savez(path, **{**good, "raw": np.zeros((3, 3, 3))})
    assert not npz_complete(path, episode)
    path.write_bytes(b"PK\x03\x04 torn")
    assert not npz_complete(path, episode)
    assert not npz_complete(tmp_path / "missing.npz", episode)


def test_read_version_leaves_out_torn_and_stale_files(tmp_path: Path) -> None:
    """The report reads a version folder a killed retrack or a full disk may have left a torn file in."""
    folder = tmp_path / "keypoints" / "v"
    folder.mkdir(parents=True)
    for k in range(3):
        (tmp_path / f"episode_00000{k}.mcap").write_bytes(b"x" * 100)
        np.savez(folder / f"episode_00000{k}.npz", frame_numbers=np.arange(2) + 2 * k,
                 keypoints=np.full((2, 3, 3), k), raw=np.full((2, 3, 3), k), edges=np.array([[0, 1], [1, 2]]),
                 rest_lengths=np.ones(2), grasp_indices=np.zeros((2, 2), int), episode_bytes=np.int64(100))
    torn = folder / "episode_000001.npz"
    torn.write_bytes(torn.read_bytes()[:200])
    (tmp_path / "episode_000002.mcap").write_bytes(b"x" * 120)  # recovered since: its result is stale
    got = read_version(tmp_path, "v", sorted(tmp_path.glob("episode_*.mcap")))
    assert sorted(got) == [0, 1] and (got[1][0] == 0).all()


def _seq(frames: list, with_states: bool, start: int) -> Sequence:
    T = len(frames)
    arrays = {"q_left": np.full((T, 7), 0.5), "q_right": np.full((T, 7), 0.25),
              "grasped_left": np.ones(T, bool), "grasped_right": np.zeros(T, bool)} if with_states else {}
    return Sequence(frames=FrameSource(lambda s: iter(frames[s:]), T), T_world_cam=np.eye(4), K=np.eye(3),
                    width=64, height=48, stamps=np.arange(T) / 30.0 + start, metadata={"episodes": [{"n": start}]},
                    frame_numbers=np.arange(start, start + T), source=Path(f"episode_{start:06d}.mcap"), **arrays)


def test_concat_sequences_reads_like_one_folder() -> None:
    a = _seq([make_frame(n) for n in range(3)], True, 0)
    b = _seq([make_frame(n) for n in range(3, 5)], False, 3)
    s = concat_sequences([a, b])
    assert len(s) == 5 and s.frame_numbers.tolist() == [0, 1, 2, 3, 4]
    assert [f.frame_number for f in s.frames] == [0, 1, 2, 3, 4]
    assert [f.frame_number for f in s.frames.iter_from(2)] == [2, 3, 4]
    assert np.isnan(s.q_left[3:]).all() and (s.q_left[:3] == 0.5).all()
    assert s.grasped_left.tolist() == [True, True, True, False, False]
    assert s.tcp_left is None and s.metadata["frames_per_file"] == [3, 2]
    b.T_world_cam = np.diag([1.0, 1.0, 1.0, 1.0]) + np.eye(4, k=3) * 0.1
    with pytest.raises(ValueError, match="calibration"):
        concat_sequences([a, b])


def test_mean_distance_over_common_frames() -> None:
    X = np.zeros((3, 3))
    assert mean_distance_mm({1: X, 2: X}, {2: X + [0.003, 0, 0], 5: X}) == pytest.approx((3.0, 1))
    assert mean_distance_mm({1: X}, {1: np.zeros((4, 3))})[1] == 0  # another keypoint count is not compared


def test_a_run_that_never_initialises_is_reported_failed(tmp_path: Path) -> None:
    """A static scene (nothing moves, so nothing is segmented): the run fails with the tracker's reason, the
    journal says so, no result file is written, and the exit code is 1."""
    from tests.test_report import _session

    session = tmp_path / "s"
    session.mkdir()
    _session(session)
    (session / "episode_000002.mcap.active").write_bytes(b"")
    r = _cli("retrack", str(session), "--workers", "1", "--version", "v", "--json", timeout=300)
    assert r.returncode == 1, r.stderr[-3000:]
    figures = json.loads(r.stdout)
    assert figures["tracked"] == 0 and len(figures["failed"]) == 1
    assert "never initialised" in next(iter(figures["failed"].values()))
    assert "episode_000002.mcap.active: unfinished episode skipped" in r.stderr
    folder = session / "keypoints" / "v"
    assert not list(folder.glob("*.npz")) and not list(folder.glob("*.tmp"))
    runs = [x for x in read_progress_journal(folder / JOURNAL_FILE) if x["type"] == "run"]
    assert [x["outcome"] for x in runs] == ["failed"] and "never initialised" in runs[0]["reason"]
    assert _cli("retrack", str(tmp_path / "nothing")).returncode == 2


def test_ray_address_without_ray_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    from orchestrator.retrack import _RayBackend

    monkeypatch.setitem(sys.modules, "ray", None)  # as if not installed
    monkeypatch.setitem(sys.modules, "ray.util.queue", None)
    with pytest.raises(RetrackError, match=r"trackdeform3d\[cluster\]"):
        _RayBackend("local", 1)
