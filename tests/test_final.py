"""Reader API (load_episode / iter_episodes / manifest), final keypoints written into episode files, inspect."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from orchestrator.config import ColorOutputConfig, load_config
from orchestrator.episode_stats import episode_stats, folder_summary
from orchestrator.final import TMP_SUFFIX, FinalKeypoints, pending_runs, rewrite_episode
from orchestrator.landing import Manifest
from orchestrator.recorder import EpisodeWriter
from tdrecord import DatasetError, iter_episodes, load_episode, read_manifest
from tests.conftest import REPO, make_frame

N = 4
EDGES = [[0, 1], [1, 2], [2, 3]]


def _state(n: int) -> dict:
    """An arm-state sample at 4x the frame rate: sample n at n / 120 s."""
    t = n / 120
    arm = {a: {"stamp": t, "q": [0.01 * n + k + 10 * i for k in range(7)], "dq": [0.001 * n - k for k in range(7)],
               "gripper_width": 0.02 + 0.001 * i + 1e-4 * n, "grasped": bool((n // 5 + i) % 2)}
           for i, a in enumerate(("left", "right"))}
    return {"stamp": t, **arm, "u": [0.1 * n + k for k in range(12)]}


def _live(n: int) -> dict:
    return {"schema": "trackdeform.Keypoints/1", "frame_number": n, "stamp": n / 30,
            "keypoints": (np.arange(N * 3).reshape(N, 3) * 0.01 + n * 0.001).tolist(), "edges": EDGES,
            "grasp_indices": {"left": 0, "right": N - 1}, "object": "rope", "category": "dlo", "status": "tracking",
            "abs_mm": 1.0, "cd_mm": 2.0, "rest_lengths": [0.0173, 0.0173, 0.0173]}


def _write(path: Path, frames: list[int], *, color: str = "raw", live: tuple[int, ...] = (1, 2, 4),
           meta: dict | None = None) -> list:
    """An episode with the given frame numbers, 4 arm states per frame and live keypoints for ``live``."""
    w = EpisodeWriter(path, "cam0", color=ColorOutputConfig(codec=color))
    written = []
    for n in frames:
        f = make_frame(n)
        written.append(f)
        w.write_frame(f, np.eye(4))
        for k in range(4):
            w.write_arm_state(_state(4 * n + k), {"left_tcp": np.eye(4), "right_tcp": np.eye(4)})
        if n in live:
            w.write_keypoints(_live(n), n / 30)
    w.close({"object": "rope", "category": "dlo", "program": "rope_swing", "speed": "medium", "repeat": 0,
             "complete": True, "fps": 30.0, **(meta or {})})
    return written


def _final(frames: list[int], files: list[Path]) -> FinalKeypoints:
    T = len(frames)
    kp = np.random.default_rng(0).uniform(-0.5, 0.5, (T, N, 3)).round(6)
    return FinalKeypoints(keypoints=kp, grasp=np.tile([1, 2], (T, 1)), frame_numbers=np.array(frames),
                          edges=np.array(EDGES), rest=np.array([0.02, 0.02, 0.02]), files=files,
                          frames_per_file=[T], object="rope", category="dlo", window=5, params={"voxel_m": 0.004})


def _messages(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    with open(path, "rb") as f:
        return [(c.topic, m.log_time, m.publish_time, m.sequence, m.data)
                for _, c, m in make_reader(f).iter_messages(log_time_order=False)]


def test_load_episode_round_trips(tmp_path: Path) -> None:
    path = tmp_path / "episode_000000.mcap"
    frames = [0, 1, 2, 4, 5]  # frame 3 dropped
    written = _write(path, frames)
    ep = load_episode(path)
    T = len(frames)
    assert ep.colour.shape == (T, 48, 64, 3) and ep.colour.dtype == np.uint8
    assert ep.depth.dtype == np.uint16 and ep.depth_scale == 0.001
    for i, f in enumerate(written):
        assert np.array_equal(ep.colour[i], f.color)
        assert np.array_equal(ep.depth[i], f.depth)  # bit-exact through 16-bit PNG
    assert ep.frame_numbers.tolist() == frames
    np.testing.assert_allclose(ep.device_stamps, [n / 30 for n in frames])
    np.testing.assert_allclose(ep.host_stamps, [n / 30 + 0.01 for n in frames])
    samples = [_state(4 * n + k) for n in frames for k in range(4)]
    S = len(samples)
    assert ep.state_stamps.shape == (S,) and ep.u.shape == (S, 12)
    for a in ("left", "right"):
        np.testing.assert_allclose(ep.q[a], [s[a]["q"] for s in samples])
        np.testing.assert_allclose(ep.dq[a], [s[a]["dq"] for s in samples])
        np.testing.assert_allclose(ep.gripper_width[a], [s[a]["gripper_width"] for s in samples])
        assert ep.grasped[a].tolist() == [s[a]["grasped"] for s in samples]
        # per frame: the sample nearest the host stamp (n / 30 + 0.01 s -> sample 4n + 1 at (4n + 1) / 120)
        np.testing.assert_allclose(ep.q_frame[a], [_state(4 * n + 1)[a]["q"] for n in frames])
    np.testing.assert_allclose(ep.u, [s["u"] for s in samples])
    np.testing.assert_allclose(ep.u_frame, [_state(4 * n + 1)["u"] for n in frames])
    assert ep.keypoints_live.shape == (T, N, 3) and ep.keypoints_final is None
    for i, n in enumerate(frames):
        if n in (1, 2, 4):
            np.testing.assert_allclose(ep.keypoints_live[i], np.round(np.asarray(_live(n)["keypoints"]), 6))
            assert ep.grasp_indices[i].tolist() == [0, N - 1]
        else:
            assert np.isnan(ep.keypoints_live[i]).all() and ep.grasp_indices[i].tolist() == [-1, -1]
    assert ep.edges.tolist() == EDGES and ep.rest_lengths.tolist() == [0.0173] * 3
    assert ep.K.shape == (3, 3) and np.allclose(ep.T_world_cam, np.eye(4))
    assert ep.metadata["object"] == "rope" and ep.metadata["n_frames"] == T
    no_images = load_episode(path, images=False)
    assert no_images.colour is None and no_images.depth is None and no_images.frame_numbers.tolist() == frames
    with pytest.raises(FileNotFoundError):
        load_episode(tmp_path / "episode_000009.mcap")


def test_final_keypoints_rewrite_copies_every_record(tmp_path: Path) -> None:
    path = tmp_path / "episode_000000.mcap"
    frames = [0, 1, 2, 3, 4, 5]
    _write(path, frames, color="h264")
    before = _messages(path)
    fk = replace(_final(frames, [path]), tangled=np.array([0, 0, 3, 1, 0, 0]))
    assert rewrite_episode(path, fk, {"keypoints": ["live", "final"], "final_keypoints": {"window": 5}}) == len(frames)
    assert rewrite_episode(path, fk, {"keypoints": ["live", "final"], "final_keypoints": {"window": 5}}) == len(frames)
    assert not list(tmp_path.glob(f"*{TMP_SUFFIX}"))
    after = _messages(path)
    copied = [m for m in after if not m[0].startswith("/keypoints/final")]
    assert copied == before  # every record verbatim (topic, times, sequence, bytes), in the same order
    assert sum(m[0] == "/keypoints/final" for m in after) == len(frames)  # the second rewrite replaced them
    assert sum(m[0] == "/keypoints/final/scene" for m in after) == len(frames)
    colour_times = [m[1] for m in before if m[0] == "/cam/cam0/color"]
    assert [m[1] for m in after if m[0] == "/keypoints/final"] == colour_times  # at each frame's log time
    # a tangled frame is flagged in its message, not passed on as a good one
    assert [json.loads(m[4])["tangled"] for m in after if m[0] == "/keypoints/final"] == [0, 0, 3, 1, 0, 0]
    ep = load_episode(path)
    np.testing.assert_allclose(ep.keypoints_final, fk.keypoints)
    assert ep.grasp_indices.tolist() == [[1, 2]] * len(frames)
    assert ep.rest_lengths.tolist() == [0.02] * 3 and ep.edges.tolist() == EDGES
    assert ep.metadata["keypoints"] == ["live", "final"] and ep.metadata["final_keypoints"] == {"window": 5}
    assert ep.metadata["object"] == "rope"  # the rest of the metadata is kept
    np.testing.assert_allclose(ep.keypoints, fk.keypoints)


def test_a_failed_rewrite_leaves_the_original(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "episode_000000.mcap"
    _write(path, [0, 1, 2])
    data = path.read_bytes()

    def full(*_a: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("orchestrator.final.os.replace", full)
    with pytest.raises(OSError, match="No space"):
        rewrite_episode(path, _final([0, 1, 2], [path]), {"keypoints": ["live", "final"]})
    assert path.read_bytes() == data and not list(tmp_path.glob(f"*{TMP_SUFFIX}"))


def test_manifest_and_iter_episodes(tmp_path: Path) -> None:
    specs = [("rope", "medium", True), ("rope", "fast", False), ("cloth", "medium", True)]
    paths = []
    for k, (obj, speed, complete) in enumerate(specs):
        p = tmp_path / f"episode_{k:06d}.mcap"
        _write(p, [3 * k, 3 * k + 1], meta={"object": obj, "speed": speed, "complete": complete, "episode_index": k})
        paths.append(p)
    assert read_manifest(tmp_path) is None
    names = [e.path.name for e in iter_episodes(tmp_path, object="rope", images=False)]  # no manifest: a scan
    assert names == ["episode_000000.mcap", "episode_000001.mcap"]
    m = Manifest(tmp_path)
    m.add(paths[:2])
    entries = read_manifest(tmp_path)
    assert [e["file"] for e in entries] == ["episode_000000.mcap", "episode_000001.mcap"]
    assert entries[1]["speed"] == "fast" and entries[1]["complete"] is False and entries[1]["keypoints"] == ["live"]
    assert entries[0]["bytes"] == paths[0].stat().st_size and entries[0]["n_frames"] == 2
    assert not (tmp_path / "manifest.json.tmp").exists()
    # the third file is not listed yet: still found; filters on the entries
    assert [e.path.name for e in iter_episodes(tmp_path, images=False)] == [p.name for p in paths]
    assert [e.path.name for e in iter_episodes(tmp_path, object="cloth", images=False)] == ["episode_000002.mcap"]
    assert [e.path.name for e in iter_episodes(tmp_path, speed=["fast"], complete=False)] == ["episode_000001.mcap"]
    assert list(iter_episodes(tmp_path, keypoints="final", images=False)) == []
    rewrite_episode(paths[0], _final([0, 1], [paths[0]]), {"keypoints": ["live", "final"]})
    m.add([paths[0]], refresh=True)
    assert [e.path.name for e in iter_episodes(tmp_path, keypoints="final", images=False)] == ["episode_000000.mcap"]
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(DatasetError, match="manifest.json: unreadable manifest"):
        list(iter_episodes(tmp_path))


def test_pending_runs_from_the_journal(tmp_path: Path) -> None:
    for k in range(5):
        (tmp_path / f"episode_{k:06d}.mcap").write_bytes(b"")
    run = {"object": "rope", "program": "p", "speed": "medium", "repeat": 0, "pass": 0, "attempt": 1}
    records = [
        {"type": "start", **run, "first_episode": 0},
        {"type": "run", **run, "outcome": "done", "episodes": ["episode_000000.mcap", "episode_000001.mcap"]},
        {"type": "final", **run, "status": "done", "episodes": ["episode_000000.mcap", "episode_000001.mcap"]},
        {"type": "start", **run, "repeat": 1, "first_episode": 2},
        {"type": "run", **run, "repeat": 1, "outcome": "done", "episodes": ["episode_000002.mcap"]},
        {"type": "final", **run, "repeat": 1, "status": "error", "episodes": ["episode_000002.mcap"]},  # retried
        {"type": "start", **run, "repeat": 2, "first_episode": 3},  # cut short by a crash: no run record
    ]
    pending = pending_runs(records, tmp_path)
    assert [(r["repeat"], [f.name for f in fs]) for r, fs in pending] == [
        (1, ["episode_000002.mcap"]), (2, ["episode_000003.mcap", "episode_000004.mcap"])]


def test_inspect_stats_and_piping_into_head(tmp_path: Path) -> None:
    a, b = tmp_path / "episode_000000.mcap", tmp_path / "episode_000001.mcap"
    _write(a, [0, 1, 2, 4, 5, 6], live=(1, 2, 4), meta={"chunk_index": 0})
    _write(b, [8, 9, 10], live=(), meta={"chunk_index": 1})
    rewrite_episode(b, _final([8, 9, 10], [b]), {"keypoints": ["live", "final"]})
    s = episode_stats(a)
    assert s["frames"] == 6 and s["frame_drops"] == 1 and s["frame_gaps"] == 1
    assert s["camera_fps"] == pytest.approx(5 / (6 / 30)) and s["max_frame_interval_ms"] == pytest.approx(2000 / 30)
    assert s["joint_states"] == 24 and s["joint_state_hz"] == pytest.approx(120 * 23 / 23.0, rel=0.2)
    assert s["keypoints"]["live"] == {"frames": 3, "coverage": 0.5, "longest_gap_frames": 2}
    assert s["keypoints"]["final"] is None
    sb = episode_stats(b)
    assert sb["keypoints"]["final"]["coverage"] == 1.0 and sb["keypoints"]["live"]["coverage"] == 0.0
    metas = [{"chunk_index": 0}, {"chunk_index": 1}]
    t = folder_summary([s, sb], metas)
    assert t["frames"] == 9 and t["frame_drops"] == 1 and t["frame_drops_between_episodes"] == 1
    assert t["final_keypoint_coverage"] == pytest.approx(3 / 9) and t["final_keypoint_files"] == 1
    cli = [sys.executable, "-m", "orchestrator.cli", "inspect"]
    out = subprocess.run([*cli, str(tmp_path)], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "1 dropped" in out.stdout and "final 3/3 frames (100.0 %)" in out.stdout
    assert "summary: 2 file(s)" in out.stdout
    js = subprocess.run([*cli, str(a), "--json"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert json.loads(js.stdout)["stats"]["frame_drops"] == 1
    if shutil.which("head") is None:
        return
    many = " ".join([str(tmp_path)] * 300)  # far more output than a pipe buffer holds
    piped = subprocess.run(f"{sys.executable} -m orchestrator.cli inspect {many} | head -n 2", shell=True,
                           capture_output=True, text=True, cwd=REPO, timeout=300)
    assert piped.returncode == 0 and len(piped.stdout.splitlines()) == 2
    assert "Traceback" not in piped.stderr and "BrokenPipe" not in piped.stderr, piped.stderr


@pytest.mark.slow
def test_sim_time_demo_every_frame_has_final_keypoints_and_resumes(demo_final_resumed: tuple[Path, str]) -> None:
    """A demo recorded with final tracking off, then resumed with it on (the shared fixture; the first session's
    episodes had no final keypoints): the first session's run is tracked on resume, the new one after it ends;
    every frame of every episode has final keypoints."""
    out, second_stdout = demo_final_resumed
    assert "final keypoints  : 2 run(s)" in second_stdout, second_stdout
    files = sorted(out.glob("episode_*.mcap"))
    assert len(files) >= 2
    for p in files:
        ep = load_episode(p)
        assert ep.keypoints_final is not None and np.isfinite(ep.keypoints_final).all(), p
        assert ep.keypoints_final.shape[0] == ep.n_frames == ep.colour.shape[0]
        assert ep.metadata["keypoints"] == ["live", "final"]
        assert ep.metadata["final_keypoints"]["window"] == 5
    finals = [json.loads(line) for line in (out / "session.journal.jsonl").read_text().splitlines()
              if json.loads(line).get("type") == "final"]
    assert sorted(e for r in finals for e in r["episodes"]) == [p.name for p in files]
    assert all(r["status"] == "done" and r["frames_with_final"] == r["frames"] for r in finals)
    assert all(0 <= r["tangled_frames"] <= r["frames"] for r in finals)  # frames flagged tangled, counted
    entries = read_manifest(out)
    assert [e["file"] for e in entries] == [p.name for p in files]
    assert all(e["keypoints"] == ["live", "final"] for e in entries)
    assert not list(out.glob(f"*{TMP_SUFFIX}"))


def test_landing_journals_final_records_and_pending_on_stop(tmp_path: Path) -> None:
    """Runs go to the background process once their files are final; its result is journaled as ``final``; a
    stop leaves the queued runs as ``final_pending`` (and pending_runs finds them for the next session)."""
    from orchestrator.config import DEFAULT_CONFIG
    from orchestrator.journal import Journal
    from orchestrator.landing import Landing
    from orchestrator.progress import Progress
    from orchestrator.summary import SessionSummary

    config = load_config(DEFAULT_CONFIG, {"bus.enabled": False})
    paths = [tmp_path / f"episode_{k:06d}.mcap" for k in range(3)]
    for k, p in enumerate(paths):
        _write(p, [3 * k, 3 * k + 1, 3 * k + 2], live=())  # noise frames: the object is never initialised
    journal = Journal.open(tmp_path, config)
    try:
        summary = SessionSummary(tmp_path)
        landing = Landing(tmp_path, config, journal, summary, Progress(enabled=False))
        run = {"object": "rope", "program": "rope_swing", "speed": "medium", "repeat": 0, "pass": 0, "attempt": 1}
        landing.run_ended(run, paths[:2])
        landing.poll([paths[0]])  # not all of the run's files are final yet: nothing to do
        assert landing.tracker is not None and landing.tracker.pending == 0
        landing.finish(paths[:2], stop_requested=False)
        finals = [r for r in journal.records if r["type"] == "final"]
        assert len(finals) == 1 and finals[0]["status"] == "failed" and "never initialised" in finals[0]["reason"]
        assert finals[0]["episodes"] == ["episode_000000.mcap", "episode_000001.mcap"]
        assert summary.final_keypoints["runs_failed"] == 1
        assert [e["file"] for e in read_manifest(tmp_path)] == [p.name for p in paths]  # all listed at start

        stopped = Landing(tmp_path, config, journal, SessionSummary(tmp_path), Progress(enabled=False))
        stopped.run_ended({**run, "repeat": 1}, paths[2:])
        stopped.finish(paths, stop_requested=True)
        pending = [r for r in journal.records if r["type"] == "final_pending"]
        assert len(pending) == 1 and pending[0]["runs"][0]["episodes"] == ["episode_000002.mcap"]
        assert not list(tmp_path.glob(f"*{TMP_SUFFIX}"))
    finally:
        journal.close()


def test_the_summary_says_how_many_final_frames_are_flagged_tangled(tmp_path: Path) -> None:
    from orchestrator.summary import SessionSummary

    summary = SessionSummary(tmp_path)
    fk = {"enabled": True, "runs_done": 1, "runs_failed": 0, "runs_pending": 0, "episodes": 2, "frames": 300,
          "frames_with_final": 300, "tangled_frames": 0}
    summary.final_keypoints = dict(fk)
    assert "final keypoints  : 1 run(s), 300 of 300 frames of 2 episode(s)\n" in summary.text() + "\n"
    summary.final_keypoints = {**fk, "tangled_frames": 12}
    assert "; 12 frame(s) flagged tangled" in summary.text()


def test_popen_nice_lowers_the_child_from_the_parent_side() -> None:
    """The final tracker and the worker start through popen_nice: the child runs NICE below the caller, with
    no preexec_fn (Python in a forked child of a threaded process can hang before exec)."""
    import os

    from orchestrator.procutil import NICE, popen_nice

    proc = popen_nice([sys.executable, "-c", "import os, sys; sys.stdin.readline(); print(os.nice(0))"],
                      stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    out, _ = proc.communicate(b"go\n", timeout=60)
    assert proc.returncode == 0
    assert int(out) == min(19, os.getpriority(os.PRIO_PROCESS, 0) + NICE)
    with pytest.raises(ValueError, match="preexec_fn"):
        popen_nice([sys.executable, "-c", "pass"], preexec_fn=lambda: None)
