"""Episode files: readable by the mcap reader, renamed only when complete, recovered after a crash."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from orchestrator.config import ColorOutputConfig
from orchestrator.recorder import EpisodeWriter, Recorder
from orchestrator.recovery import recover_active
from tdrecord import read_episode_metadata
from tests.conftest import REPO, make_frame

RAW_COLOR = ColorOutputConfig(codec="raw")


def _write(path: Path, n: int) -> EpisodeWriter:
    w = EpisodeWriter(path, "cam0", color=RAW_COLOR)  # random colour: exact
    for i in range(n):
        w.write_frame(make_frame(i), np.eye(4))
        w.write_arm_state({"stamp": i / 30, "left": {}, "right": {}, "u": [0.0] * 12})
    return w


def test_episode_round_trip(tmp_path: Path) -> None:
    w = _write(tmp_path / "episode_000000.mcap", 5)
    assert w.active_path.exists() and not w.path.exists()
    final = w.close({"object": "rope", "speed": "slow"})
    assert final.exists() and not w.active_path.exists()
    meta = read_episode_metadata(final)
    assert meta["object"] == "rope" and meta["n_frames"] == 5 and meta["last_frame"] == 4
    with open(final, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        colors = [m for _, c, _, m in reader.iter_decoded_messages(topics=["/cam/cam0/color"])]
    assert len(colors) == 5 and colors[0].encoding == "rgb8" and colors[0].width == 64
    np.testing.assert_array_equal(
        np.frombuffer(colors[3].data, np.uint8).reshape(48, 64, 3), make_frame(3).color
    )


def test_refuses_to_overwrite_a_finished_episode(tmp_path: Path) -> None:
    p = tmp_path / "episode_000000.mcap"
    _write(p, 1).close({})
    try:
        EpisodeWriter(p, "cam0")
    except FileExistsError as e:
        assert "refusing to overwrite" in str(e)
    else:  # pragma: no cover
        raise AssertionError("overwrote a finished episode")


def test_recover_after_sigkill(tmp_path: Path) -> None:
    """A writer killed mid-episode leaves .active; recovery rewrites every complete chunk."""
    script = textwrap.dedent(f"""
        import sys, os, signal, numpy as np
        sys.path.insert(0, {str(REPO)!r})
        from orchestrator.recorder import EpisodeWriter
        from tests.conftest import make_frame
        w = EpisodeWriter(__import__('pathlib').Path({str(tmp_path)!r}) / 'episode_000003.mcap', 'cam0')
        for i in range(400):
            w.write_frame(make_frame(i, 320, 240), np.eye(4))
        w._file.flush(); os.fsync(w._file.fileno())
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True)
    assert proc.returncode == -signal.SIGKILL
    assert (tmp_path / "episode_000003.mcap.active").exists()
    (tmp_path / "episode_000004.mcap.active").write_bytes(b"\x89MCAP0\r\n")  # nothing readable
    results = dict((p.name, o) for p, o in recover_active(tmp_path))
    assert results["episode_000003.mcap"].startswith("recovered")
    assert results["episode_000004.mcap.active"].startswith("quarantined")
    assert (tmp_path / "quarantine" / "episode_000004.mcap.active").exists()
    rec = tmp_path / "episode_000003.mcap"
    with open(rec, "rb") as f:
        reader = make_reader(f)
        n = sum(1 for _ in reader.iter_messages(topics=["/cam/cam0/frame_info"]))
    assert 0 < n <= 400
    assert read_episode_metadata(rec)["recovered"] is True
    assert not list(tmp_path.glob("*.active"))


def test_recorder_thread_routes_late_keypoints(tmp_path: Path) -> None:
    rec = Recorder("cam0", close_grace=5)
    rec.open_episode(tmp_path / "episode_000000.mcap", {"n": 0})
    for i in range(3):
        rec.frame(make_frame(i), np.eye(4))
    rec.close_episode({"complete": True})
    rec.open_episode(tmp_path / "episode_000001.mcap", {"n": 1})
    rec.frame(make_frame(3), np.eye(4))
    rec.keypoints({"frame_number": 2, "stamp": 2 / 30, "keypoints": [[0, 0, 0]], "edges": []})  # late, ep 0
    rec.keypoints({"frame_number": 3, "stamp": 3 / 30, "keypoints": [[0, 0, 0]], "edges": []})
    rec.keypoints({"frame_number": 99, "stamp": 3.0, "keypoints": [], "edges": []})
    rec.stop()
    assert not rec.errors
    assert rec.keypoints_written == 2 and rec.keypoints_unmatched == 1
    assert [p.name for p in rec.finished] == ["episode_000000.mcap", "episode_000001.mcap"]
    assert read_episode_metadata(rec.finished[0])["complete"] is True
    assert read_episode_metadata(rec.finished[1])["complete"] is False
    with open(rec.finished[0], "rb") as f:
        kps = [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/keypoints"])]
    assert [k["frame_number"] for k in kps] == [2]
