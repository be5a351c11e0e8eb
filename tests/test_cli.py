"""The trackdeform command line: help, validate, inspect, recover, watch."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from orchestrator.bus import Bus
from orchestrator.cli import main
from orchestrator.config import BusConfig
from orchestrator.recorder import EpisodeWriter
from tdcommon.wire import encode_keypoints
from tests.conftest import REPO, make_frame

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
    expected = "no library program 'no_such_program'; available: branched_lift, cloth_fold, rope_swing"
    assert expected in capsys.readouterr().out


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


def test_watch_prints_live_keypoints(port: int) -> None:
    endpoint = f"tcp/127.0.0.1:{port}"
    with Bus(BusConfig(listen=[endpoint]), "mock") as bus:
        proc = subprocess.Popen(
            [*CLI, "watch", "--connect", endpoint, "--count", "2", "--seconds", "30"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        try:
            deadline = time.monotonic() + 30
            n = 0
            while proc.poll() is None and time.monotonic() < deadline:
                bus.put(bus.key("keypoints"), encode_keypoints(
                    frame_number=n, stamp=n / 30, keypoints=np.zeros((20, 3)), edges=np.zeros((19, 2), int),
                    grasp_indices={"left": 0, "right": 19}, object_name="rope", category="dlo",
                    status="tracking", abs_mm=1.25, cd_mm=2.5,
                ))
                n += 1
                time.sleep(0.1)
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    lines = [ln for ln in out.splitlines() if ln.startswith("frame")]
    assert len(lines) == 2, err
    assert "rope/dlo" in lines[0] and "N= 20" in lines[0] and "Abs  1.25 mm" in lines[0] and "L=0 R=19" in lines[0]
