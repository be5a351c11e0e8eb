"""The trackdeform command line: help, validate, inspect, recover, watch."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from orchestrator.cli import main
from orchestrator.cli_tracking import format_keypoints_line
from orchestrator.recorder import EpisodeWriter
from tdcommon.wire import check_keypoints
from tests.conftest import NO_LIVE_INIT, REPO, make_frame, mock_yaml

CLI = [sys.executable, "-m", "orchestrator.cli"]


def test_help_lists_the_commands(capsys) -> None:
    try:
        main(["--help"])
    except SystemExit as e:
        assert e.code == 0
    out = capsys.readouterr().out
    for cmd in ("demo", "run", "validate", "inspect", "recover", "program", "worker", "watch", "track"):
        assert cmd in out


def test_validate_mock_and_a_bad_config(tmp_path: Path, capsys) -> None:
    assert main(["validate", str(REPO / "configs" / "mock.yaml")]) == 0
    assert "rope_swing (rope) at medium" in capsys.readouterr().out
    bad = tmp_path / "bad.yaml"
    bad.write_text((REPO / "configs" / "mock.yaml").read_text().replace("fps: 30", "fps: 0"))
    assert main(["validate", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.yaml:" in err and "station.camera.fps" in err and "greater than 0" in err and "(got 0)" in err


def test_validate_reports_a_missing_program(tmp_path: Path, capsys) -> None:
    cfg = tmp_path / "c.yaml"
    cfg.write_text((REPO / "configs" / "mock.yaml").read_text().replace("[rope_swing]", "[no_such_program]"))
    assert main(["validate", str(cfg)]) == 1
    out = capsys.readouterr().out
    assert "no library program 'no_such_program'; available: branched_lift, cloth_fold, rope_swing" in out


def test_inspect_and_recover(tmp_path: Path, capsys) -> None:
    w = EpisodeWriter(tmp_path / "episode_000000.mcap", "cam0")
    for i in range(3):
        w.write_frame(make_frame(i), np.eye(4))
    w.close({"object": "rope"})
    assert main(["inspect", str(tmp_path / "episode_000000.mcap")]) == 0
    out = capsys.readouterr().out
    assert "/cam/cam0/color" in out and "3 messages" in out and 'object = "rope"' in out
    assert main(["recover", str(tmp_path)]) == 0
    assert "nothing to recover" in capsys.readouterr().out


@pytest.mark.slow
def test_watch_prints_live_keypoints(tmp_path: Path, port: int) -> None:
    """The real path: a real-time demo (session + its tracking worker, two processes) and `watch` in a third
    process, which knows only the session's endpoint, prints the worker's keypoints."""
    endpoint = f"tcp/127.0.0.1:{port}"
    out = tmp_path / "demo"
    # routing is the point here: the worker initialises on the run itself, and the run is not tracked again after
    # the stop (final keypoints are tested in test_final.py)
    cfg = mock_yaml(tmp_path / "mock_no_live_init.yaml", {**NO_LIVE_INIT, "tracking.final": False})
    demo = subprocess.Popen([*CLI, "demo", "--seconds", "120", "--out", str(out), "--port", str(port),
                             "--config", str(cfg)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        watch = subprocess.run([*CLI, "watch", "--connect", endpoint, "--count", "90", "--seconds", "100", "--json"],
                               capture_output=True, text=True, timeout=150)
        deadline = time.monotonic() + 120  # the first sets may be the live initialisation's: stop once it records
        while not list(out.glob("episode_*.mcap*")) and time.monotonic() < deadline and demo.poll() is None:
            time.sleep(0.2)
        stop = subprocess.run([*CLI, "ctl", "stop", "--connect", endpoint, "--station", "mock"],
                              capture_output=True, text=True, timeout=60)
        demo_out, _ = demo.communicate(timeout=120)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
    msgs = [json.loads(ln) for ln in watch.stdout.splitlines() if ln.startswith("{")]
    worker_log = (out / "worker.log").read_text() if (out / "worker.log").exists() else ""
    assert len(msgs) == 90, watch.stderr + demo_out + worker_log
    assert stop.returncode == 0 and "stopping" in stop.stdout, stop.stdout + stop.stderr
    assert demo.returncode == 0, demo_out
    session_ids = {m["session_id"] for m in msgs}
    assert len(session_ids) == 1 and all(m["run_id"] and m["object"] == "rope" for m in msgs)
    assert [m["frame_number"] for m in msgs] == sorted({m["frame_number"] for m in msgs})  # every set, in order
    assert all(check_keypoints(m) is None for m in msgs)
    tracked = [m for m in msgs if m["status"] in ("init", "tracking", "degraded")]
    assert tracked and len(tracked[-1]["keypoints"]) == 20, msgs[-1]["status"]
    line = format_keypoints_line(tracked[-1])
    assert "rope/dlo" in line and "N= 20" in line
    events = [json.loads(ln) for ln in (out / "events.jsonl").read_text().splitlines()]
    assert any(e["event"] == "ctl" and e["command"] == "stop" for e in events)
    assert events[-1]["event"] == "state" and events[-1]["state"] == "done"


def test_track_starts_without_the_heavy_imports() -> None:
    """``trackdeform track``'s modules and the helpers it calls import neither open3d nor scipy.signal (with
    scipy.stats): ~1.4 s of start-up, a tenth of a 150-frame clip's whole command."""
    code = (
        "import sys\n"
        "import orchestrator.cli_tracking, orchestrator.worker, tdrecord.sequence, tracking.metrics, "
        "tracking.offline, tracking.pipeline, tdcommon.objects, tdrecord\n"
        "from tdcommon.robot import panda_link_meshes\n"
        "from tracking.anchors import _savgol_weights\n"
        "from tracking.segmentation import voxel_downsample\n"
        "import numpy as np\n"
        "assert sum(len(m.triangles) for m in panda_link_meshes()) > 2000\n"
        "_savgol_weights(9)\n"
        "voxel_downsample(np.random.default_rng(0).random((100, 3)), 0.1)\n"
        "print(sorted({'open3d', 'scipy.signal', 'scipy.stats'} & set(sys.modules)))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"
