"""``program teach``: scripted stdin on fake arms moved between commands, and the CLI as a subprocess."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from drivers.base import Arm
from orchestrator.config import DEFAULT_CONFIG, load_config
from orchestrator.teach import INTERRUPTED, NOTHING_SAVED, SAVED, SAVED_WITH_PROBLEMS, teach_station
from tdcommon.robot import PandaKinematics
from trajectories.program import ProgramError, library_path, load_program
from trajectories.safety import check_program
from trajectories.timing import SLOW, time_program

REPO = Path(__file__).resolve().parent.parent
ROPE = load_program(library_path("rope_swing"))


@pytest.fixture(scope="module")
def config():  # noqa: ANN201 - orchestrator.config.Config
    return load_config(DEFAULT_CONFIG, {"station.camera.width": 160, "station.camera.height": 120,
                                        "tracking.enabled": False, "bus.enabled": False})


def guide_to_waypoints(plan: dict[int, int]):  # noqa: ANN201 - GuideHook
    """A guide hook putting both fake arms at rope_swing waypoint ``plan[step]`` before command ``step``."""

    def guide(step: int, arms: dict[str, Arm]) -> None:
        if step in plan:
            w = ROPE.waypoints[plan[step]]
            arms["left"].guide_to(np.asarray(w.left))  # type: ignore[attr-defined]
            arms["right"].guide_to(np.asarray(w.right))  # type: ignore[attr-defined]

    return guide


def test_teach_records_guided_waypoints_and_gripper_toggles(config, tmp_path: Path) -> None:
    script = ["", "g l", "", "", "u", "", "g left", "", "q", "ignored after q"]
    # step index -> rope_swing waypoint the arms are guided to before that command is read
    guide = guide_to_waypoints({0: 0, 2: 1, 3: 3, 5: 2, 7: 3})
    out = io.StringIO()
    path = tmp_path / "taught.yaml"
    rc = teach_station(config, io.StringIO("\n".join(script) + "\n"), out, out_path=path, category="dlo",
                       guide=guide)
    text = out.getvalue()
    assert rc == SAVED, text
    program = load_program(path)
    assert program.name == "taught" and program.category == "dlo"
    assert len(program.waypoints) == 4  # the undone waypoint (guided to waypoint 3) is gone
    for wp, src in zip(program.waypoints, (0, 1, 2, 3), strict=True):
        np.testing.assert_allclose(wp.q(), ROPE.waypoints[src].q(), atol=2e-6)
    states = [(g["left"].state, g["right"].state) for g in program.gripper_states()]
    assert states == [("closed", "closed"), ("open", "closed"), ("open", "closed"), ("closed", "closed")]
    assert [w.dwell for w in program.waypoints] == [0.0, 1.0, 0.0, 1.0]  # a pause where a gripper changes
    timed = time_program(program, SLOW)
    assert check_program(timed, {n: getattr(config.station, n).arm.base.matrix() for n in ("left", "right")}).ok
    assert timed.duration == pytest.approx(3 * 4.0 + 2 * 1.0, abs=1e-3)
    # one line per waypoint with the TCP positions (world frame), and the undo
    lines = [ln for ln in text.splitlines() if ln.startswith("waypoint ")]
    assert [ln.split(":")[0] for ln in lines] == ["waypoint 0", "waypoint 1", "waypoint 2", "waypoint 2", "waypoint 3"]
    kin = PandaKinematics(config.station.left.arm.base.matrix())
    x, y, z = kin.tcp_pose(np.asarray(ROPE.waypoints[1].left))[:3, 3]
    assert f"left TCP ({x:+.3f}, {y:+.3f}, {z:+.3f}) m gripper open (changes here)" in lines[1]
    assert "removed waypoint 2" in text and f"saved {path}" in text


def test_teach_saves_a_bad_program_with_a_warning(config, tmp_path: Path) -> None:
    bad = np.asarray(ROPE.waypoints[1].left)
    bad[3] = -3.2  # joint 4 beyond the Panda's lower limit (-3.0718 rad)

    def guide(step: int, arms: dict[str, Arm]) -> None:
        if step == 1:
            arms["left"].guide_to(bad)  # type: ignore[attr-defined]

    out = io.StringIO()
    path = tmp_path / "bad.json"
    rc = teach_station(config, io.StringIO("\n\n"), out, out_path=path, name="bad", guide=guide)  # EOF = q
    text = out.getvalue()
    assert rc == SAVED_WITH_PROBLEMS, text
    assert "end of input: saving" in text
    assert "warning: waypoint 1.left[3] = -3.2 rad is below the Panda limit" in text  # at record time
    assert "problem(s) found" in text and "saved" in text and "anyway" in text
    assert path.is_file()
    with pytest.raises(ProgramError, match=r"waypoints\[1\]\.left\[3\]"):
        load_program(path)  # saved so the session is not lost, but refused until fixed


def test_teach_interrupt_and_empty_session_save_nothing(config, tmp_path: Path) -> None:
    class CtrlC(io.StringIO):
        def readline(self, *_: object) -> str:  # type: ignore[override]
            if self.tell() >= 1:  # Ctrl-C while waiting for the second command
                raise KeyboardInterrupt
            return super().readline()

    out = io.StringIO()
    path = tmp_path / "interrupted.yaml"
    assert teach_station(config, CtrlC("\n\n"), out, out_path=path) == INTERRUPTED
    assert "quit without saving (1 waypoint(s) discarded)" in out.getvalue()
    assert not path.exists()

    out = io.StringIO()
    assert teach_station(config, io.StringIO("g r\nfoo\nq\n"), out, out_path=path) == NOTHING_SAVED
    text = out.getvalue()
    assert "right gripper opening" in text and "unknown command 'foo'" in text and "nothing saved" in text
    assert not path.exists()


def test_teach_cli_subprocess(tmp_path: Path) -> None:
    path = tmp_path / "cli.yaml"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [sys.executable, "-m", "orchestrator.cli", "program", "teach", "--config", str(DEFAULT_CONFIG),
         "--out", str(path), "--name", "cli_taught", "--category", "cloth"],
        input="\ng r\n\nq\n", capture_output=True, text=True, timeout=60, cwd=tmp_path, env=env,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "teaching on simulated station with cloth" in proc.stdout
    program = load_program(path)
    assert program.name == "cli_taught" and program.category == "cloth" and len(program.waypoints) == 2
    assert program.waypoints[1].grippers["right"].state == "open"
    assert time_program(program, SLOW).duration == pytest.approx(4.0 + 1.0, abs=1e-3)
