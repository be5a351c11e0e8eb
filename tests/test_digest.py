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
        assert got is not None
        assert sorted(got, key=lambda x: (x[1], x[0])) == sorted(_mcap_small_channels(e), key=lambda x: (x[1], x[0]))
        assert {t for t, _, _ in got} == {"/cam/cam0/frame_info", "/keypoints"}
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
