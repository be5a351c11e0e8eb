"""Episode digests (``tdrecord.digest``): written beside each finished episode, they hold exactly the episode's
small JSON channels, and the report reads the same run from them as from the MCAP files."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from orchestrator.report import group_runs, read_color, read_color_at, read_recorded
from tdrecord.digest import DIGEST_SUFFIX, digest_path, digest_topic, read_digest
from tests.test_report import _session


def _mcap_small_channels(path: Path) -> list[tuple[str, int, dict]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        topics = [c.topic for c in reader.get_summary().channels.values() if digest_topic(c.topic)]
        return [(ch.topic, int(m.log_time), json.loads(m.data)) for _, ch, m in reader.iter_messages(topics=topics)]


def _fields(folder: Path) -> list[dict]:
    runs = group_runs(sorted(folder.glob("episode_*.mcap")))
    for r in runs:
        read_recorded(r)
    return [{"t": r.t, "abs": r.abs_mm, "cd": r.cd_mm, "kp": np.stack(r.keypoints).tolist(), "fn": r.frame_numbers,
             "frames": r.frames, "statuses": r.statuses, "edges": r.edges.tolist(),
             "times": {k: (Path(p).name, a, b) for k, (p, a, b) in r.log_times.items()}} for r in runs]


def test_the_digest_holds_the_small_channels_and_the_report_reads_the_same(tmp_path: Path) -> None:
    session = tmp_path / "s"
    session.mkdir()
    _session(session)
    episodes = sorted(session.glob("episode_*.mcap"))
    assert [digest_path(e).name for e in episodes] == sorted(p.name for p in session.glob(f"*{DIGEST_SUFFIX}"))
    for e in episodes:
        got = read_digest(e)
        assert got is not None and got.gt_error_mm == {}  # no ground truth in these episodes
        assert sorted(got.messages, key=lambda x: (x[1], x[0])) == sorted(_mcap_small_channels(e),
                                                                          key=lambda x: (x[1], x[0]))
        assert {t for t, _, _ in got.messages} == {"/cam/cam0/frame_info", "/keypoints"}
    with_digest = _fields(session)

    plain = tmp_path / "plain"  # the same episodes without their digests: read from the MCAP files
    plain.mkdir()
    for e in episodes:
        shutil.copy(e, plain / e.name)
    assert _fields(plain) == with_digest

    # a digest that belongs to another episode, or a torn one, is not used
    shutil.copy(digest_path(episodes[0]), digest_path(plain / episodes[1].name))
    assert read_digest(plain / episodes[1].name) is None
    digest_path(plain / episodes[0].name).write_bytes(digest_path(episodes[0]).read_bytes()[:50])
    assert read_digest(plain / episodes[0].name) is None
    assert _fields(plain) == with_digest


def test_a_thumbnail_decodes_from_its_keyframe_only(tmp_path: Path) -> None:
    session = tmp_path / "s"
    session.mkdir()
    _session(session)
    run = group_runs(sorted(session.glob("episode_*.mcap")))[0]
    read_recorded(run)
    for fn in (0, 7, 13):
        path, log_time, key_time = run.log_times[fn]
        assert key_time <= log_time
        np.testing.assert_array_equal(read_color_at(path, log_time, key_time), read_color(path, fn))
    assert read_color_at(path, log_time + 1, key_time) is None  # no frame logged then


def test_thumbnails_move_to_nearby_keyframes_and_stay_spread() -> None:
    from orchestrator.report import RunData, _thumbnail_frames

    r = RunData(key=(), object="o", category="dlo", program="p", speed="s", repeat=0, attempt=1, plan_pass=0,
                episodes=[])
    r.t, r.frame_numbers = list(range(300)), list(range(300))
    r.log_times = {n: (Path("e.mcap"), n, n - n % 30) for n in range(300)}  # a keyframe every 30 frames
    assert _thumbnail_frames(r, 4) == [0, 90, 210, 299]  # 100 -> 90, 199 -> 210; 299 is 29 from 270: stays
    r.t, r.frame_numbers = r.t[:23], r.frame_numbers[:23]
    r.log_times = {n: (Path("e.mcap"), n, 17 if n >= 17 else 0) for n in range(23)}
    assert _thumbnail_frames(r, 4) == [0, 7, 17, 22]  # 15 -> 17 (half the spacing), 7 stays: no keyframe near


def test_a_new_episode_of_the_same_name_drops_a_stale_digest(tmp_path: Path) -> None:
    from orchestrator.recorder import EpisodeWriter
    from tests.conftest import make_frame

    path = tmp_path / "episode_000000.mcap"
    w = EpisodeWriter(path, "cam0")
    w.write_frame(make_frame(0), np.eye(4))
    w.close({})
    assert read_digest(path) is not None
    path.unlink()  # deleted by hand; the name is recorded again
    w = EpisodeWriter(path, "cam0")
    assert not digest_path(path).exists()
    w.abort()


def test_ground_truth_goes_into_the_digest_as_the_errors_the_report_would_compute(tmp_path: Path) -> None:
    """A mock episode's digest holds each keypoint set's ground-truth error instead of the dense true samples;
    the report's GT figures from it equal those computed from the MCAP file's ground-truth messages."""
    from orchestrator.recorder import EpisodeWriter
    from tdcommon.types import CameraIntrinsics, GroundTruth, RGBDFrame
    from tests.test_report import T_CAM, _kp_message

    intr = CameraIntrinsics.from_fov(160, 120, 69.0)
    s = np.linspace(-0.2, 0.2, 300)
    session = tmp_path / "s"
    session.mkdir()
    for e in range(2):
        w = EpisodeWriter(session / f"episode_{e:06d}.mcap", "cam0")
        for n in range(e * 8, e * 8 + 8):
            centre = np.c_[s, 0.02 * np.sin(8 * s + 0.3 * n), np.zeros_like(s)]
            gt = GroundTruth(centre[::30], np.c_[np.arange(9), np.arange(1, 10)], centre, 0.004, np.array([0, 9]),
                             "dlo")
            w.write_frame(RGBDFrame(np.zeros((120, 160, 3), np.uint8), np.full((120, 160), 1000, np.uint16), 0.001,
                                    intr, 10.0 + n / 30.0, 10.002 + n / 30.0, n, ground_truth=gt), T_CAM)
            X = centre[::60] + [0.0, 0.0, 0.001 * n]  # off the centreline by n mm
            if n != 3:  # a frame without keypoints
                w.write_keypoints(_kp_message(n, X, 1.0, 2.0), 10.0 + n / 30.0)
        w.close({"object": "rope", "category": "dlo", "program": "p", "speed": "fast", "repeat": 0, "run_index": 0,
                 "attempt": 1, "plan_pass": 0, "episode_index": e, "complete": True, "fault": False})
    episodes = sorted(session.glob("episode_*.mcap"))
    d = read_digest(episodes[1])
    assert d is not None and sorted(d.gt_error_mm) == list(range(8, 16))
    assert "/ground_truth/keypoints" not in {t for t, _, _ in d.messages}
    assert "/ground_truth/keypoints" in {t for t, _, _ in _mcap_small_channels(episodes[1])}
    plain = tmp_path / "plain"
    plain.mkdir()
    for e in episodes:
        shutil.copy(e, plain / e.name)
    runs = {}
    for folder in (session, plain):
        (run,) = group_runs(sorted(folder.glob("episode_*.mcap")))
        read_recorded(run)
        runs[folder] = run
    a, b = np.asarray(runs[session].gt_mm), np.asarray(runs[plain].gt_mm)
    assert len(a) == 15 and np.isfinite(a).all()
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert a[0] < 0.5 and a[-1] > 10.0  # the keypoints drift off the centreline, frame by frame
